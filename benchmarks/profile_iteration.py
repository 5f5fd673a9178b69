"""Where PPOPeVFA's time goes beside SB3 PPO's: cProfile of whole iterations, the same settings for both.

Each algorithm first learns ``--warmup`` iterations (PeVFA's first has no history; its historical updates start
after 5000 steps), then ``--iterations`` more under cProfile;
prints the CPU time (``time.process_time``) and the cumulative CPU time of the parts of an iteration. cProfile's own
overhead inflates Python-heavy parts: compare the two columns, not the absolute seconds.

    python benchmarks/profile_iteration.py --env Hopper-v5 --iterations 4
    # rl-zoo3's tuned entry (256x256 networks, 512-step rollouts, VecNormalize)
    python benchmarks/profile_iteration.py --env Walker2d-v5 --iterations 16 --warmup 10 \
        --conf benchmarks/hyperparams/zoo_tuned.yml
"""

import argparse
import cProfile
import pathlib
import pstats
import time
from typing import Any

import torch as th
import yaml
from stable_baselines3 import PPO
from stable_baselines3.common.env_util import make_vec_env
from stable_baselines3.common.vec_env import VecNormalize
from torch import nn

from sb3_pevfa import PPOPeVFA

#: (label, file suffix, function name) of the parts reported (SB3's rollout for PPO, the fast path's for PPOPeVFA)
PARTS = [
    ("rollout", ("on_policy_algorithm.py", "fast_path.py"), "collect_rollouts"),
    ("env steps", "dummy_vec_env.py", "step_wait"),
    ("PPO update", "ppo.py", "train"),
    ("evaluate_actions", "policies.py", "evaluate_actions"),
    ("history updates", "algorithm.py", "_train_on_history"),
    ("objectives", "algorithm.py", "_train_objectives"),
    ("backward passes", "__init__.py", "backward"),
]


def zoo_entry(conf: pathlib.Path | None, env_id: str) -> tuple[object, dict[str, Any]]:
    """The env (a ``VecNormalize`` where the entry says ``normalize``) and the algorithm's keyword arguments of an
    rl-zoo3 hyperparameter file's entry for ``env_id``; SB3's defaults without a file."""
    if conf is None:
        return env_id, {}
    entry = dict(yaml.safe_load(conf.read_text())[env_id])
    env = make_vec_env(env_id, n_envs=entry.pop("n_envs", 1), seed=0)
    if entry.pop("normalize", False):
        env = VecNormalize(env)
    for key in ("policy", "n_timesteps"):
        entry.pop(key, None)
    if isinstance(entry.get("policy_kwargs"), str):  # rl-zoo3 writes them as Python
        entry["policy_kwargs"] = eval(entry["policy_kwargs"], {"nn": nn, "dict": dict})
    return env, entry


def profile(
    algo: type, env_id: str, iterations: int, conf: pathlib.Path | None = None, warmup: int = 1
) -> tuple[float, dict[str, float]]:
    env, kwargs = zoo_entry(conf, env_id)
    model = algo("MlpPolicy", env, seed=0, **kwargs)
    steps = model.n_steps * model.n_envs
    model.learn(warmup * steps)
    profiler = cProfile.Profile(time.process_time)  # CPU time of this process: a busy second core does not count
    start = time.process_time()
    profiler.enable()
    model.learn(iterations * steps, reset_num_timesteps=False)
    profiler.disable()
    cpu = time.process_time() - start
    stats = pstats.Stats(profiler).stats  # type: ignore[attr-defined]
    parts = {}
    for label, suffix, name in PARTS:
        total = sum(
            row[3] for (file, _, function), row in stats.items() if file.endswith(suffix) and function == name
        )  # str.endswith takes one suffix or a tuple of them
        if total:
            parts[label] = total
    return cpu, parts


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--env", default="Hopper-v5")
    parser.add_argument("--iterations", type=int, default=4)
    parser.add_argument("--conf", type=pathlib.Path, default=None, help="rl-zoo3 hyperparameters (the env's entry)")
    parser.add_argument("--warmup", type=int, default=1, help="iterations learned before the profile")
    args = parser.parse_args()
    th.set_num_threads(1)
    algorithms = (("PPO", PPO), ("PPOPeVFA", PPOPeVFA))
    results = {name: profile(algo, args.env, args.iterations, args.conf, args.warmup) for name, algo in algorithms}
    labels = [label for label, *_ in PARTS if any(label in parts for _, parts in results.values())]
    print(f"| {args.env}, {args.iterations} iterations | " + " | ".join(results) + " |")
    print("|---|" + "---|" * len(results))
    print("| CPU time (s) | " + " | ".join(f"{cpu:.1f}" for cpu, _ in results.values()) + " |")
    for label in labels:
        print(f"| {label} | " + " | ".join(f"{parts.get(label, 0.0):.1f}" for _, parts in results.values()) + " |")


if __name__ == "__main__":
    main()
