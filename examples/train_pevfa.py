"""Train PPOPeVFA on a Gymnasium task, evaluate it, and save the model and its policy history.

python examples/train_pevfa.py --env CartPole-v1 --timesteps 30000
python examples/train_pevfa.py --env Hopper-v5 --timesteps 100000 --representation spr   # needs mujoco
"""

import argparse
import pathlib

import torch as th
from stable_baselines3.common.env_util import make_vec_env
from stable_baselines3.common.evaluation import evaluate_policy

from sb3_pevfa import REPRESENTATIONS, PPOPeVFA
from sb3_pevfa.extras import exit_without_env_extra


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--env", default="CartPole-v1")
    parser.add_argument("--timesteps", type=int, default=30_000)
    parser.add_argument("--representation", default="opr", choices=REPRESENTATIONS)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--out", type=pathlib.Path, default=pathlib.Path("runs/example"))
    parser.add_argument("--tiny", action="store_true", help="1k steps in 256-step rollouts (a smoke test)")
    args = parser.parse_args()
    exit_without_env_extra(args.env, f"examples/train_pevfa.py --env {args.env}")
    th.set_num_threads(1)
    kwargs = {}
    if args.tiny:
        args.timesteps, kwargs = 1024, dict(n_steps=256, history_learning_starts=0)

    env = make_vec_env(args.env, n_envs=1, seed=args.seed)
    model = PPOPeVFA("MlpPolicy", env, representation=args.representation, seed=args.seed, verbose=1, **kwargs)
    model.learn(args.timesteps)
    mean, std = evaluate_policy(model, make_vec_env(args.env, n_envs=1, seed=args.seed + 1), n_eval_episodes=10)
    # PPO trains whole rollouts of n_steps: the steps taken, not the ones asked for
    print(f"{args.env} PPOPeVFA({args.representation}) after {model.num_timesteps} steps: return {mean:.1f} +- {std:.1f}")
    print(model.history)
    args.out.mkdir(parents=True, exist_ok=True)
    model.save(args.out / "model")
    model.save_history(args.out / "history")
    print(f"saved {args.out / 'model.zip'} and {args.out / 'history.npz'}")


if __name__ == "__main__":
    main()
