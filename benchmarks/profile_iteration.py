"""Where PPOPeVFA's time goes beside SB3 PPO's: cProfile of whole iterations, the same settings for both.

Each algorithm first learns one iteration (PeVFA's first has no history), then ``--iterations`` more under cProfile;
prints the CPU time (``time.process_time``) and the cumulative time of the parts of an iteration. cProfile's own
overhead inflates Python-heavy parts: compare the two columns, not the absolute seconds.

    python benchmarks/profile_iteration.py --env Hopper-v5 --iterations 4
"""

import argparse
import cProfile
import pstats
import time

import torch as th
from stable_baselines3 import PPO

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


def profile(algo: type, env_id: str, iterations: int) -> tuple[float, dict[str, float]]:
    model = algo("MlpPolicy", env_id, seed=0)
    steps = model.n_steps * model.n_envs
    model.learn(steps)
    profiler = cProfile.Profile()
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
    args = parser.parse_args()
    th.set_num_threads(1)
    results = {name: profile(algo, args.env, args.iterations) for name, algo in (("PPO", PPO), ("PPOPeVFA", PPOPeVFA))}
    labels = [label for label, *_ in PARTS if any(label in parts for _, parts in results.values())]
    print(f"| {args.env}, {args.iterations} iterations | " + " | ".join(results) + " |")
    print("|---|" + "---|" * len(results))
    print("| CPU time (s) | " + " | ".join(f"{cpu:.1f}" for cpu, _ in results.values()) + " |")
    for label in labels:
        print(f"| {label} | " + " | ".join(f"{parts.get(label, 0.0):.1f}" for _, parts in results.values()) + " |")


if __name__ == "__main__":
    main()
