"""Global generalization (paper Fig. 3a): PeVFAs trained on the values of 80 % of random tiny policies in the Point
Walker, evaluated on the unseen 20 % (MSE and rank correlation), with raw parameters (RPR) and OPR.

    python examples/global_generalization.py --n-policies 2000 --n-trajectories 20 --epochs 5   # a few CPU minutes
    python examples/global_generalization.py --n-policies 20000 --n-trajectories 50             # the paper's scale
    python examples/global_generalization.py --tiny

Needs the diagnostics extra: pip install -e ".[diagnostics]"
"""

from sb3_pevfa.extras import exit_without_extra

exit_without_extra("diagnostics", "examples/global_generalization.py")

import argparse
import json
import pathlib

import torch as th

from sb3_pevfa.diagnostics import plot_global_generalization, run_global_generalization


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--n-policies", type=int, default=2_000)
    parser.add_argument("--n-trajectories", type=int, default=20)
    parser.add_argument("--horizon", type=int, default=10)
    parser.add_argument("--epochs", type=int, default=5)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--out", type=pathlib.Path, default=pathlib.Path("runs/global_generalization"))
    parser.add_argument("--tiny", action="store_true", help="100 policies, 1 epoch (a smoke test)")
    args = parser.parse_args()
    th.set_num_threads(1)
    if args.tiny:
        args.n_policies, args.n_trajectories, args.epochs = 100, 5, 1

    results = run_global_generalization(
        n_policies=args.n_policies,
        n_trajectories=args.n_trajectories,
        horizon=args.horizon,
        epochs=args.epochs,
        seed=args.seed,
    )
    args.out.mkdir(parents=True, exist_ok=True)
    plot_global_generalization(results, str(args.out / "global_generalization.png"))
    summary = {
        "n_policies": args.n_policies,
        "n_trajectories": args.n_trajectories,
        "horizon": args.horizon,
        "epochs": args.epochs,
        "seed": args.seed,
        "results": [
            {k: getattr(r, k) for k in ("representation", "train_mse", "test_mse", "spearman", "seconds")} for r in results
        ],
    }
    (args.out / "global_generalization.json").write_text(json.dumps(summary, indent=1))
    for r in results:
        scores = f"train MSE {r.train_mse:.3f}, test MSE {r.test_mse:.3f}, Spearman {r.spearman:.2f}"
        print(f"{r.representation}: {scores} ({r.seconds:.0f} s)")
    print(f"figure: {args.out / 'global_generalization.png'}")


if __name__ == "__main__":
    main()
