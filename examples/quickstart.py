"""Quickstart: train PPOPeVFA, save the model and its policy history, load both, and go on training.

python examples/quickstart.py                 # Pendulum-v1, 20k steps
python examples/quickstart.py --tiny          # seconds (CI)
"""

import argparse
import pathlib

import torch as th
from stable_baselines3.common.evaluation import evaluate_policy

from sb3_pevfa import PPOPeVFA


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--env", default="Pendulum-v1")
    parser.add_argument("--timesteps", type=int, default=20_000)
    parser.add_argument("--out", type=pathlib.Path, default=pathlib.Path("runs/quickstart"))
    parser.add_argument("--tiny", action="store_true", help="1k steps with 256-step rollouts (a smoke test)")
    args = parser.parse_args()
    th.set_num_threads(1)  # one thread is faster for small networks on CPU
    small = dict(n_steps=256, batch_size=64, history_learning_starts=0) if args.tiny else {}
    timesteps = 1024 if args.tiny else args.timesteps
    args.out.mkdir(parents=True, exist_ok=True)

    model = PPOPeVFA("MlpPolicy", args.env, seed=0, **small)
    model.learn(timesteps)
    model.save(args.out / "model")
    model.save_history(args.out / "history")  # large: saved apart from the model, like a replay buffer

    model = PPOPeVFA.load(args.out / "model", env=None)  # an env id model rebuilds its env when it learns on
    model.load_history(args.out / "history.npz")
    model.learn(timesteps, reset_num_timesteps=False)
    mean, std = evaluate_policy(model, model.get_env(), n_eval_episodes=3 if args.tiny else 10)
    print(f"{args.env}: {model.num_timesteps} steps, {model.history.n_policies} policies in the history, "
          f"return {mean:.1f} +- {std:.1f}")  # fmt: skip


if __name__ == "__main__":
    main()
