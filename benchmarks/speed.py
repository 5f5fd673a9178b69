"""Speed: environment steps per second of SB3 PPO vs PPOPeVFA at identical PPO hyperparameters, one torch thread.

The two are measured alternately in one process (A B A B ...), each measurement a ``learn`` of ``--steps`` steps
from the state after an untimed warm-up of ``--warmup`` steps, and the median ratio and its spread are reported,
with a breakdown of PPOPeVFA's time (rollout, on-policy update, historical updates, encoder calls) and the env-only
rate (random actions through the same VecEnv: the limit).

The cost of a historical update grows with the number of distinct policies in its batch, so the warm-up decides
what is measured: 6144 steps (3 policies in the history) is the start of a run, 200k steps (the history full at
its default 200k samples, ~98 policies) is its steady state. Each warm-up is trained once (seed 0) and cached
under ``--cache`` (model and history); every repeat loads it with a fresh env seeded by the repeat.

    python benchmarks/speed.py --env Hopper-v5 CartPole-v1 --warmup 6144 --repeats 5 --out runs/speed
    python benchmarks/speed.py --env Hopper-v5 CartPole-v1 --warmup 200000 --repeats 5 --out runs/speed
"""

import argparse
import functools
import json
import pathlib
import time

import numpy as np
import torch as th
from stable_baselines3 import PPO
from stable_baselines3.common.env_util import make_vec_env

from sb3_pevfa import PPOPeVFA


class Timer:
    """Accumulates the wall time of wrapped callables, by name."""

    def __init__(self):
        self.seconds: dict[str, float] = {}

    def wrap(self, name: str, function):
        @functools.wraps(function)
        def timed(*args, **kwargs):
            start = time.perf_counter()
            try:
                return function(*args, **kwargs)
            finally:
                self.seconds[name] = self.seconds.get(name, 0.0) + time.perf_counter() - start

        return timed


def env_only_rate(env_id: str, steps: int) -> float:
    env = make_vec_env(env_id, n_envs=1, seed=0)
    env.reset()
    actions = [env.action_space.sample() for _ in range(1000)]
    start = time.perf_counter()
    for i in range(steps):
        env.step(np.array([actions[i % 1000]]))
    return steps / (time.perf_counter() - start)


def warmed_up(name: str, env_id: str, warmup: int, cache: pathlib.Path, seed: int):
    """A model trained for ``warmup`` steps (cached), loaded on a fresh env seeded by ``seed``."""
    algo = PPO if name == "ppo" else PPOPeVFA
    path = cache / f"{env_id}_{name}_{warmup}"
    if not path.with_suffix(".zip").exists():
        model = algo("MlpPolicy", make_vec_env(env_id, n_envs=1, seed=0), seed=0)
        model.learn(warmup)
        model.save(path)
        if name == "ppo_pevfa":
            model.save_history(path.with_suffix(".history.npz"))
    model = algo.load(path, env=make_vec_env(env_id, n_envs=1, seed=seed), seed=seed)
    if name == "ppo_pevfa":
        model.load_history(path.with_suffix(".history.npz"))
    return model


def measure(model, steps: int, timer: Timer | None = None) -> float:
    if timer is not None:
        model.collect_rollouts = timer.wrap("rollout", model.collect_rollouts)
        model.train = timer.wrap("train", model.train)
        if isinstance(model, PPOPeVFA):
            model._train_on_history = timer.wrap("history update", model._train_on_history)
            encoder = model.policy.representation
            encoder.forward = timer.wrap("encoder forward", encoder.forward)
    start = time.perf_counter()
    model.learn(steps, reset_num_timesteps=False)
    return steps / (time.perf_counter() - start)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--env", nargs="+", default=["Hopper-v5", "CartPole-v1"])
    parser.add_argument("--steps", type=int, default=8192)
    parser.add_argument("--warmup", type=int, default=6144, help="untimed steps first (historical updates start at 5k)")
    parser.add_argument("--cache", type=pathlib.Path, default=pathlib.Path("runs/speed_cache"), help="warmed-up models")
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument("--out", type=pathlib.Path, default=pathlib.Path("runs/speed"))
    args = parser.parse_args()
    th.set_num_threads(1)
    args.out.mkdir(parents=True, exist_ok=True)
    args.cache.mkdir(parents=True, exist_ok=True)
    for env_id in args.env:
        rates: dict[str, list[float]] = {"ppo": [], "ppo_pevfa": []}
        breakdown = Timer()
        for repeat in range(args.repeats):
            for name in ("ppo", "ppo_pevfa"):  # A B A B ...
                model = warmed_up(name, env_id, args.warmup, args.cache, seed=repeat)
                if name == "ppo_pevfa":
                    n_policies = model.history.n_policies
                rates[name].append(measure(model, args.steps, breakdown if name == "ppo_pevfa" else None))
        ratios = np.array(rates["ppo_pevfa"]) / np.array(rates["ppo"])
        seconds = breakdown.seconds
        total = seconds["rollout"] + seconds["train"]
        parts = {  # shares of PPOPeVFA's learn time; the encoder's forward calls happen inside the other parts
            "rollout": seconds["rollout"] / total,
            "on-policy update": (seconds["train"] - seconds["history update"]) / total,
            "history update": seconds["history update"] / total,
            "encoder forward (inside the above)": seconds["encoder forward"] / total,
        }
        result = {
            "env": env_id,
            "steps": args.steps,
            "warmup": args.warmup,
            "repeats": args.repeats,
            "history_policies_at_start": n_policies,
            "ppo_steps_per_s": rates["ppo"],
            "pevfa_steps_per_s": rates["ppo_pevfa"],
            "ratio_median": float(np.median(ratios)),
            "ratio_min": float(ratios.min()),
            "ratio_max": float(ratios.max()),
            "env_only_steps_per_s": env_only_rate(env_id, args.steps),
            "pevfa_seconds": seconds,
            "pevfa_shares": parts,
        }
        (args.out / f"{env_id}_warmup{args.warmup}.json").write_text(json.dumps(result, indent=1))
        print(
            f"{env_id} after {args.warmup} steps: PPO {np.median(rates['ppo']):.0f} steps/s, PPOPeVFA "
            f"{np.median(rates['ppo_pevfa']):.0f} steps/s, ratio median {result['ratio_median']:.2f} "
            f"[{result['ratio_min']:.2f}, {result['ratio_max']:.2f}], env alone {result['env_only_steps_per_s']:.0f} steps/s"
        )
        print("  PPOPeVFA time: " + ", ".join(f"{k} {v:.0%}" for k, v in parts.items()))


if __name__ == "__main__":
    main()
