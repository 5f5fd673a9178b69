"""Per run of a local-generalization campaign (its journal): the best and final evaluation, the mean errors of PeVFA
and of the conventional critic before and after the critic update, the geometric mean of the per-iteration ratio
PeVFA / conventional (over the run, its first half and its second half) and how often PeVFA was closer.

    python docs/notes/scripts/local_generalization_runs.py --campaign table1-authors-local-generalization
"""

import argparse
import pathlib
import sys

import numpy as np

ROOT = pathlib.Path(__file__).resolve().parents[3]
sys.path.insert(0, str(ROOT / "benchmarks"))

from engine.results import collect  # noqa: E402


def geometric_mean(ratio: np.ndarray) -> float:
    return float(np.exp(np.mean(np.log(ratio)))) if ratio.size else np.nan


def row(task: str, run: dict) -> str:
    series = {key: np.asarray(values, float) for key, values in run["local_generalization"].items()}
    cells = [task, str(run["seed"]), f"{run['max_average_return']:.0f}", f"{run['final_return']:.0f}"]
    for when in ("before", "after"):
        pevfa, vfa = series[f"pevfa_{when}"], series[f"vfa_{when}"]
        valid = np.isfinite(pevfa) & np.isfinite(vfa) & (vfa > 0) & (pevfa > 0)
        ratio = pevfa[valid] / vfa[valid]
        half = ratio.size // 2
        halves = f"({geometric_mean(ratio[:half]):.2f}, {geometric_mean(ratio[half:]):.2f})"
        cells += [f"{pevfa[valid].mean():.0f} / {vfa[valid].mean():.0f}", f"{geometric_mean(ratio):.2f} {halves}",
                  f"{np.mean(ratio < 1):.0%}"]  # fmt: skip
    cells.insert(4, str(int(np.isfinite(series["pevfa_before"]).sum())))
    return "| " + " | ".join(cells) + " |"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--campaign", default="table1-authors-local-generalization")
    parser.add_argument("--storage", default=None)
    args = parser.parse_args()
    runs, _, notes, _ = collect([args.campaign], args.storage)
    print("| task | seed | max average return | final | iterations | error before: PeVFA / conventional "
          "| ratio before (1st half, 2nd half) | PeVFA closer before | error after | ratio after (halves) "
          "| PeVFA closer after |")  # fmt: skip
    print("|---" * 11 + "|")
    for task, by_variant in runs.items():
        for variant_runs in by_variant.values():
            for run in sorted(variant_runs, key=lambda r: r["seed"]):
                if run.get("local_generalization"):
                    print(row(task, run))
    for note in notes:
        print(f"note: {note}")


if __name__ == "__main__":
    main()
