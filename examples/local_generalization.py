"""Local generalization on your task (paper Fig. 3b / 8): PeVFA's V(s, chi) vs a conventional V(s) trained side by
side, error against the returns the current policy collected, before and after each critic update.

    python examples/local_generalization.py --env InvertedPendulum-v5 --timesteps 100000
    python examples/local_generalization.py --tiny          # seconds, for CI

Needs the diagnostics extra: pip install -e ".[diagnostics]"
"""

from sb3_pevfa.extras import exit_without_extra

exit_without_extra("diagnostics", "examples/local_generalization.py")

import argparse
import pathlib

import numpy as np
import torch as th
from stable_baselines3.common.logger import configure

from sb3_pevfa import REPRESENTATIONS, PPOPeVFA
from sb3_pevfa.diagnostics import LocalGeneralizationCallback, plot_local_generalization
from sb3_pevfa.diagnostics.local_generalization import read_scalars


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--env", default="InvertedPendulum-v5")
    parser.add_argument("--timesteps", type=int, default=100_000)
    parser.add_argument("--representation", default="opr", choices=REPRESENTATIONS)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--out", type=pathlib.Path, default=pathlib.Path("runs/local_generalization"))
    parser.add_argument("--tiny", action="store_true", help="CartPole-v1, 512 steps (a smoke test)")
    args = parser.parse_args()
    th.set_num_threads(1)
    kwargs = {}
    if args.tiny:
        args.env, args.timesteps = "CartPole-v1", 512
        kwargs = dict(n_steps=128, batch_size=64, n_epochs=2, history_learning_starts=0)

    model = PPOPeVFA("MlpPolicy", args.env, representation=args.representation, seed=args.seed, **kwargs)
    logs = args.out / "logs"
    model.set_logger(configure(str(logs), ["csv", "stdout"] if not args.tiny else ["csv"]))
    model.learn(args.timesteps, callback=LocalGeneralizationCallback())
    png = plot_local_generalization(logs, args.out / "local_generalization.png", title=f"{args.env}, {args.representation}")
    scalars = read_scalars(logs)
    means = {
        key: np.nanmean(scalars[f"pevfa/local_gen/{key}"])
        for key in ("pevfa_before", "vfa_before", "pevfa_after", "vfa_after")
    }
    before = scalars["pevfa/local_gen/pevfa_before"] < scalars["pevfa/local_gen/vfa_before"]
    print(", ".join(f"mean {key} MSE {value:.3g}" for key, value in means.items()))
    print(f"PeVFA's error before the update is below the conventional critic's at {np.nanmean(before):.0%} of iterations")
    print(f"figure: {png}")


if __name__ == "__main__":
    main()
