"""Zero-shot policy values: rank a run's checkpoints by the PeVFA's predicted value (no rollout) and compare with
their measured returns (Spearman rank correlation).

    python examples/zero_shot_values.py --env CartPole-v1 --timesteps 50000 --checkpoints 10
    python examples/zero_shot_values.py --tiny

Needs the diagnostics extra: pip install -e ".[diagnostics]"
"""

from sb3_pevfa.extras import exit_without_extra

exit_without_extra("diagnostics", "examples/zero_shot_values.py")

import argparse
import pathlib

import numpy as np
import torch as th
from scipy.stats import spearmanr
from stable_baselines3.common.callbacks import CheckpointCallback
from stable_baselines3.common.env_util import make_vec_env
from stable_baselines3.common.evaluation import evaluate_policy

from sb3_pevfa import PPOPeVFA
from sb3_pevfa.diagnostics import predict_policy_values


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--env", default="CartPole-v1")
    parser.add_argument("--timesteps", type=int, default=50_000)
    parser.add_argument("--checkpoints", type=int, default=10)
    parser.add_argument("--eval-episodes", type=int, default=10)
    parser.add_argument("--representation", default="opr")
    parser.add_argument("--out", type=pathlib.Path, default=pathlib.Path("runs/zero_shot"))
    parser.add_argument("--tiny", action="store_true", help="a 1k-step CartPole run with 4 checkpoints (a smoke test)")
    args = parser.parse_args()
    th.set_num_threads(1)
    kwargs = {}
    if args.tiny:
        args.timesteps, args.checkpoints, args.eval_episodes = 1024, 4, 2
        kwargs = dict(n_steps=64, batch_size=32, history_learning_starts=0)

    model = PPOPeVFA("MlpPolicy", args.env, representation=args.representation, seed=0, **kwargs)
    every = max(args.timesteps // args.checkpoints, model.n_steps)
    model.learn(args.timesteps, callback=CheckpointCallback(every, str(args.out / "checkpoints"), name_prefix="pevfa"))
    # states to value the checkpoints at: start states of the task
    env = make_vec_env(args.env, n_envs=1, seed=123)
    starts = np.concatenate([env.reset() for _ in range(64)])
    paths = sorted((args.out / "checkpoints").glob("pevfa_*_steps.zip"), key=lambda p: int(p.stem.split("_")[1]))
    predicted, measured = [], []
    for path in paths:
        checkpoint = PPOPeVFA.load(path)
        predicted.append(predict_policy_values(model, checkpoint, starts).mean())
        measured.append(evaluate_policy(checkpoint, env, n_eval_episodes=args.eval_episodes)[0])
        print(f"{path.name}: predicted value {predicted[-1]:.1f}, measured return {measured[-1]:.1f}")
    rho = spearmanr(predicted, measured).statistic if len(paths) > 2 else float("nan")
    print(f"Spearman rank correlation of predicted values and measured returns over {len(paths)} checkpoints: {rho:.2f}")

    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(5, 4))
    ax.scatter(measured, predicted)
    for path, x, y in zip(paths, measured, predicted):
        ax.annotate(path.stem.split("_")[1], (x, y), fontsize=7)
    title = f"{args.env}: Spearman {rho:.2f}"
    if args.tiny:  # 1k steps: the checkpoints barely differ, and so would any ranking of them
        title += " (smoke run: too short to rank)"
        print("a smoke run (--tiny): too short for the checkpoints' ranking to mean anything")
    ax.set(xlabel="measured return", ylabel="PeVFA predicted value (start states)", title=title)
    ax.ticklabel_format(useOffset=False)  # the values themselves on the axes, not an offset
    fig.tight_layout()
    fig.savefig(args.out / "zero_shot_values.png", dpi=100)
    print(f"figure: {args.out / 'zero_shot_values.png'}")


if __name__ == "__main__":
    main()
