"""SB3's training logs of PPO in the paper and the authors' protocols (``grid_run_signals.py``'s ``progress.csv``),
summarised per window of env steps: iterations, env steps per iteration, the actor's
approximate KL per iteration and per 1000 env steps, the clip fraction, the std at the window's end, the critic's
explained variance and the episode length.

    python docs/notes/scripts/ppo_two_protocols.py docs/results/notes/ppo-two-protocols --window 100000
"""

import argparse
import csv
import math
import pathlib
import sys

ROOT = pathlib.Path(__file__).resolve().parents[3]
sys.path.insert(0, str(ROOT / "benchmarks"))

from engine.results import collect  # noqa: E402

#: Env steps at which the stored grid runs' best evaluation so far is printed
MARKS = (100_000, 200_000, 300_000, 500_000, 1_000_000)


def rows_of(path: pathlib.Path) -> list[dict[str, float]]:
    with path.open() as handle:
        return [{k: float(v) if v not in ("", None) else math.nan for k, v in row.items()} for row in csv.DictReader(handle)]


def mean(values: list[float]) -> float:
    values = [v for v in values if not math.isnan(v)]
    return sum(values) / len(values) if values else math.nan


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("folder", type=pathlib.Path)
    parser.add_argument("--window", type=int, default=100_000)
    parser.add_argument("--campaigns", nargs="*", default=["table1", "table1-authors"], help="the grids' PPO runs")
    parser.add_argument("--tasks", nargs="*", default=["Hopper-v5", "HalfCheetah-v5"])
    args = parser.parse_args()
    print("| campaign | task | runs | " + " | ".join(f"best by {m // 1000}k" for m in MARKS) + " |")
    print("|---|---|---|" + "---|" * len(MARKS))
    for name in args.campaigns:
        runs, *_ = collect([name], None)
        for task in args.tasks:
            curves = [r["curve"] for r in runs.get(task, {}).get("ppo", [])]
            best = [mean([max([v for s, v in zip(c["steps"], c["mean"]) if s <= m], default=math.nan) for c in curves])
                    for m in MARKS]  # fmt: skip
            print(f"| {name} | {task} | {len(curves)} | " + " | ".join(f"{b:.0f}" for b in best) + " |")
    print()
    print(
        "| run | env steps | iterations | env steps / iteration | approx KL / iteration "
        "| KL per 1000 env steps | clip fraction | std at the end | explained variance | episode length |"
    )
    print("|---|---|---|---|---|---|---|---|---|---|")
    for path in sorted(args.folder.glob("*/*/progress.csv")):
        rows = [r for r in rows_of(path) if not math.isnan(r.get("train/approx_kl", math.nan))]
        previous_steps = 0.0
        start = 0
        while start + args.window <= rows[-1]["time/total_timesteps"]:  # whole windows
            window = [r for r in rows if start < r["time/total_timesteps"] <= start + args.window]
            if not window:
                break
            steps = window[-1]["time/total_timesteps"] - previous_steps
            kl = [r["train/approx_kl"] for r in window]
            print(
                f"| {path.parent.parent.name} | {start // 1000}-{(start + args.window) // 1000}k | {len(window)} "
                f"| {steps / len(window):.0f} | {mean(kl):.4f} "
                f"| {1000 * sum(kl) / steps:.4f} | {mean([r['train/clip_fraction'] for r in window]):.3f} "
                f"| {window[-1]['train/std']:.3f} | {mean([r['train/explained_variance'] for r in window]):.2f} "
                f"| {mean([r['rollout/ep_len_mean'] for r in window]):.0f} |"
            )
            previous_steps = window[-1]["time/total_timesteps"]
            start += args.window


if __name__ == "__main__":
    main()
