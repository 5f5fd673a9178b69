"""Speed in rl-zoo3's settings: whole runs of SB3's algorithm and its PeVFA class, alternately in one process.

A setting is a task's rl-zoo3 hyperparameter entry for SB3's algorithm and the package's shipped entry for its PeVFA
class (``n_envs``, ``normalize``, ``policy_kwargs``... as rl-zoo3 reads them, VecNormalize with the entry's gamma
as rl-zoo3 builds it; ``--options`` on top of the PeVFA entry); each repeat trains a fresh model of each (seed = the
repeat) for ``--steps`` env steps, SB3's first, and times its ``learn`` in CPU seconds of this process
(``time.process_time``) and wall-clock seconds, one torch thread. The ratio is PeVFA's steps per CPU-second over
SB3's in the same repeat; its median and range over the repeats are reported.

SACPeVFA's and TD3PeVFA's snapshots' updates draw ``history_batch_policies`` snapshots (8) once as many exist, fewer
before: with a snapshot per 1000 gradient steps a short run pays a cheaper update than a long one. Each of their runs
records the snapshots its updates drew on average (``snapshots_per_update``) and says where it is short of the long
run's; ``--options '{"snapshot_freq": 100}'`` gives a short run a long run's updates (8 snapshots from its 700th
gradient step on).

    # rl-zoo3's shipped A2C settings on CartPole-v1 (8 envs, 5-step rollouts): A2C vs A2CPeVFA's shipped entry
    python benchmarks/speed_zoo.py --setting a2c-cartpole --steps 100000 --repeats 5
    # rl-zoo3's tuned Hopper-v5 PPO (256x256, n_steps 512, VecNormalize): PPO vs PPOPeVFA's shipped entry
    python benchmarks/speed_zoo.py --setting ppo-hopper-tuned --steps 60000 --repeats 5
    # rl-zoo3's Hopper SAC entry (SB3's SAC defaults): SAC vs SACPeVFA's shipped entry, 1000 random steps first (the
    # entry's 10000 would be most of a short run) for both, a long run's 8 snapshots per update for SACPeVFA
    python benchmarks/speed_zoo.py --setting sac-hopper --steps 6000 --repeats 3 --overrides '{"learning_starts": 1000}' \
        --options '{"snapshot_freq": 100}'
    # rl-zoo3's Hopper TD3 entry (400x300, Gaussian action noise 0.1): TD3 vs TD3PeVFA's shipped entry, the same way
    python benchmarks/speed_zoo.py --setting td3-hopper --steps 6000 --repeats 3 --overrides '{"learning_starts": 1000}' \
        --options '{"snapshot_freq": 100}'
"""

import argparse
import json
import pathlib
import time
from typing import Any

import numpy as np
import rl_zoo3
import torch as th
import yaml
from stable_baselines3 import A2C, PPO, SAC, TD3
from stable_baselines3.common.env_util import make_vec_env
from stable_baselines3.common.evaluation import evaluate_policy
from stable_baselines3.common.noise import NormalActionNoise, OrnsteinUhlenbeckActionNoise
from stable_baselines3.common.vec_env import VecNormalize
from torch import nn

from sb3_pevfa import A2CPeVFA, PPOPeVFA, SACPeVFA, TD3PeVFA
from sb3_pevfa.pevfa.off_policy import OffPolicyPeVFA

ROOT = pathlib.Path(__file__).resolve().parents[1]
ZOO = pathlib.Path(rl_zoo3.__file__).parent / "hyperparams"
OURS = ROOT / "hyperparams"
TUNED = ROOT / "benchmarks" / "hyperparams" / "zoo_tuned.yml"  # rl-zoo3 tuned PPO entries, v5 tasks
#: setting -> the env, SB3's class and its hyperparameter file, the PeVFA class and its file (the package's shipped
#: entries: what ``python -m sb3_pevfa.train --algo ppo_pevfa|a2c_pevfa`` trains)
SETTINGS = {
    "a2c-cartpole": ("CartPole-v1", A2C, ZOO / "a2c.yml", A2CPeVFA, OURS / "a2c_pevfa.yml"),
    "ppo-hopper-tuned": ("Hopper-v5", PPO, TUNED, PPOPeVFA, OURS / "ppo_pevfa.yml"),
    "sac-hopper": ("Hopper-v5", SAC, ZOO / "sac.yml", SACPeVFA, OURS / "sac_pevfa.yml"),
    "td3-hopper": ("Hopper-v5", TD3, ZOO / "td3.yml", TD3PeVFA, OURS / "td3_pevfa.yml"),
}


def entry_of(path: pathlib.Path, env_id: str) -> dict[str, Any]:
    """The entry as rl-zoo3 uses it: the algorithm's arguments, and ``n_envs`` / ``normalize`` for the env (a v5
    task reads rl-zoo3's v4 entry where it has no v5 one, as the package's shipped files do)."""
    entries = yaml.load(path.read_text(), Loader=yaml.UnsafeLoader)  # rl-zoo3's loader (!!float)
    entry = dict(entries[env_id] if env_id in entries else entries[env_id.replace("-v5", "-v4")])
    entry.pop("n_timesteps", None)
    if isinstance(entry.get("policy_kwargs"), str):
        entry["policy_kwargs"] = eval(entry["policy_kwargs"], {"nn": nn, "dict": dict})  # as rl-zoo3 does
    return entry


def make_model(algorithm: type, entry: dict[str, Any], env_id: str, seed: int):
    entry = dict(entry)
    n_envs, normalize, policy = entry.pop("n_envs", 1), entry.pop("normalize", False), entry.pop("policy")
    env = make_vec_env(env_id, n_envs=n_envs, seed=seed)
    noise_type = entry.pop("noise_type", None)
    if noise_type is not None:  # rl-zoo3's action noise ("normal" / "ornstein-uhlenbeck", std per dimension)
        sigma = entry.pop("noise_std") * np.ones(env.action_space.shape[0])
        noises = {"normal": NormalActionNoise, "ornstein-uhlenbeck": OrnsteinUhlenbeckActionNoise}
        noise = [cls for name, cls in noises.items() if name in noise_type.strip()]
        if not noise:
            raise ValueError(f"Unknown noise_type {noise_type!r}, valid choices: {sorted(noises)}")
        entry["action_noise"] = noise[0](mean=np.zeros_like(sigma), sigma=sigma)
    if normalize:
        kwargs = normalize if isinstance(normalize, dict) else {}
        env = VecNormalize(env, **({"gamma": entry["gamma"]} if "gamma" in entry else {}), **kwargs)
    return algorithm(policy, env, seed=seed, **entry)


def timed_run(algorithm: type, entry: dict[str, Any], env_id: str, seed: int, steps: int, episodes: int) -> dict[str, float]:
    """One run's CPU and wall-clock seconds of ``learn``, and then (untimed) the mean return of ``episodes``
    deterministic episodes of the trained policy on an env seeded with ``seed + 10000``."""
    model = make_model(algorithm, entry, env_id, seed)
    drawn = snapshots_drawn(model)
    cpu, wall = time.process_time(), time.perf_counter()
    model.learn(steps)
    cpu, wall = time.process_time() - cpu, time.perf_counter() - wall
    env = model.get_env()
    if isinstance(env, VecNormalize):
        env.training = False  # evaluate in the run's statistics, without moving them
    returns, _ = evaluate_policy(model, env, n_eval_episodes=episodes, return_episode_rewards=True)
    run = {"steps": model.num_timesteps, "cpu_s": cpu, "wall_s": wall, "steps_per_cpu_s": model.num_timesteps / cpu,
           "final_return": float(np.mean(returns))}  # fmt: skip
    if drawn is not None:  # the snapshots its updates drew on average, and a long run's
        run["snapshots_per_update"] = float(np.mean(drawn)) if drawn else 0.0
        run["batch_policies"] = min(model.history_batch_policies, model.history_max_policies)
    return run


def snapshots_drawn(model) -> list[int] | None:
    """For an off-policy PeVFA model, the list its snapshots' updates append the number of snapshots they draw to
    (None for other models)."""
    if not isinstance(model, OffPolicyPeVFA):
        return None
    drawn: list[int] = []
    sample = model.history.sample_policy_ids

    def counted(n: int) -> np.ndarray:
        ids = sample(n)
        drawn.append(len(ids))
        return ids

    model.history.sample_policy_ids = counted
    return drawn


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--setting", choices=sorted(SETTINGS), required=True)
    parser.add_argument("--steps", type=int, default=100_000)
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument("--eval-episodes", type=int, default=10, help="deterministic episodes after each run (untimed)")
    parser.add_argument("--options", type=json.loads, default={}, help="PeVFA options beside the entry, as JSON")
    parser.add_argument("--overrides", type=json.loads, default={}, help="arguments of both entries, as JSON")
    parser.add_argument("--out", type=pathlib.Path, default=None, help="a JSON file for every run and the summary")
    args = parser.parse_args()
    th.set_num_threads(1)
    env_id, base, base_file, pevfa, pevfa_file = SETTINGS[args.setting]
    entries = {
        "base": {**entry_of(base_file, env_id), **args.overrides},
        "pevfa": {**entry_of(pevfa_file, env_id), **args.overrides, **args.options},
    }
    runs: dict[str, list[dict[str, float]]] = {"base": [], "pevfa": []}
    for seed in range(args.repeats):
        for name, algorithm in (("base", base), ("pevfa", pevfa)):  # A B A B ...
            runs[name].append(timed_run(algorithm, entries[name], env_id, seed, args.steps, args.eval_episodes))
            run = runs[name][-1]
            drawn = "snapshots_per_update" in run and f", {run['snapshots_per_update']:.1f} snapshots per update"
            print(f"seed {seed} {algorithm.__name__}: {run['steps_per_cpu_s']:.0f} steps/CPU-s, return "
                  f"{run['final_return']:.0f}{drawn or ''}", flush=True)  # fmt: skip
    ratios = np.array([p["steps_per_cpu_s"] / b["steps_per_cpu_s"] for b, p in zip(runs["base"], runs["pevfa"])])
    wall = np.array([b["wall_s"] / p["wall_s"] for b, p in zip(runs["base"], runs["pevfa"])])
    summary = {
        "setting": args.setting, "entries": {k: {n: repr(v) for n, v in e.items()} for k, e in entries.items()},
        "env": env_id, "steps": args.steps,
        "base": base.__name__, "pevfa": pevfa.__name__, "runs": runs, "ratio_median": float(np.median(ratios)),
        "ratio_min": float(ratios.min()), "ratio_max": float(ratios.max()), "wall_ratio_median": float(np.median(wall)),
    }  # fmt: skip
    print(
        f"{args.setting}: {base.__name__} {np.median([r['steps_per_cpu_s'] for r in runs['base']]):.0f}, "
        f"{pevfa.__name__} {np.median([r['steps_per_cpu_s'] for r in runs['pevfa']]):.0f} steps per CPU-second "
        f"(medians of {args.repeats}); ratio median {summary['ratio_median']:.2f} [{summary['ratio_min']:.2f}, "
        f"{summary['ratio_max']:.2f}], wall-clock {summary['wall_ratio_median']:.2f}; final return "
        + ", ".join(
            f"{cls.__name__} {np.mean([r['final_return'] for r in runs[n]]):.0f}"
            for n, cls in (("base", base), ("pevfa", pevfa))
        )
    )
    off_policy = [run for run in runs["pevfa"] if "batch_policies" in run]
    short = [run for run in off_policy if run["snapshots_per_update"] < 0.9 * run["batch_policies"]]
    if short:
        drawn = [run["snapshots_per_update"] for run in short]
        print(f"{len(short)} of the {pevfa.__name__} runs drew {min(drawn):.1f}-{max(drawn):.1f} snapshots per update on "
              f"average, a long run {short[0]['batch_policies']}: a short run's cost; --options "
              """'{"snapshot_freq": 100}' gives it a long run's updates""")  # fmt: skip
    if args.out is not None:
        args.out.parent.mkdir(parents=True, exist_ok=True)
        args.out.write_text(json.dumps(summary, indent=1))


if __name__ == "__main__":
    main()
