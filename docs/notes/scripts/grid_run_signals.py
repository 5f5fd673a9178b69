"""A grid run of a campaign again, its first ``--steps`` env steps, with SB3's training logs kept (``progress.csv``).

The run is the campaign engine's own (``benchmarks/engine/training.py``: the same model, env seeds and evaluations),
so its evaluations are the stored run's up to round-off; the script prints both curves to check it. The logs (the
critic's explained variance, the actor's KL and clip fraction, the std, chi's norm) are what the grid does not keep.

    python docs/notes/scripts/grid_run_signals.py --campaign table1-authors --task Hopper-v5 --variant opr-e2e \
        --seed 1 --steps 60000 --out docs/results/notes/authors-hopper-seed1
"""

import argparse
import pathlib
import sys

from stable_baselines3.common.logger import configure

ROOT = pathlib.Path(__file__).resolve().parents[3]
sys.path.insert(0, str(ROOT / "benchmarks"))

from engine import definitions, training  # noqa: E402
from engine.results import collect  # noqa: E402


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--campaign", required=True)
    parser.add_argument("--task", required=True)
    parser.add_argument("--variant", required=True)
    parser.add_argument("--seed", type=int, required=True)
    parser.add_argument("--steps", type=int, required=True)
    parser.add_argument("--out", type=pathlib.Path, required=True)
    args = parser.parse_args()
    grid = definitions.CAMPAIGNS[args.campaign]
    if args.variant in definitions.LOCAL_GENERALIZATION:
        parser.error("the diagnostic's variants log through the engine's own logger: choose another variant")
    campaign = definitions.Campaign(
        grid.protocol, (args.task,), (args.variant,), (args.seed,), args.steps, grid.eval_freq, grid.eval_episodes
    )
    folder = args.out / f"{args.variant}-seed{args.seed}"
    algorithm = training.algorithm_of(grid.protocol, args.variant)
    learn = algorithm.learn

    def logged_learn(model, *learn_args, **kwargs):
        model.set_logger(configure(str(folder), ["csv"]))
        return learn(model, *learn_args, **kwargs)

    algorithm.learn = logged_learn  # type: ignore[method-assign]
    result = training.train(campaign, args.task, args.variant, args.seed)
    runs, *_ = collect([args.campaign], None)
    stored = [r for r in runs.get(args.task, {}).get(args.variant, []) if r["seed"] == args.seed]
    again = result["curve"]["mean"]
    print("this run:  ", [round(x, 1) for x in again])
    if stored:
        print("stored run:", [round(x, 1) for x in stored[0]["curve"]["mean"][: len(again)]])


if __name__ == "__main__":
    main()
