"""The report's figures: learning curves per env step and per CPU-second with the performance profile (one PNG, a
column per task), the local-generalization diagnostic over training, and the baseline's curves in two protocols."""

import pathlib
import warnings

import numpy as np

from . import aggregate
from .results import Runs
from .tables import compared_variants, diagnosed, table1_order


def local_generalization_curves(series: list[dict[str, list[float]]], window: int = 25) -> dict[str, np.ndarray]:
    """A task's diagnostic runs over training: the env steps and, before and after the critic update, the PeVFA's
    error over the conventional critic's, as a geometric mean over runs smoothed by a centered moving geometric mean
    over ``window`` points (non-finite errors left out). Off-policy runs line up by snapshot (``policy_id``: a resumed
    run lacks the windows open at its checkpoint, an unscored window is missing too); on-policy ones on a grid of env
    steps, every median iteration size up to the shortest run's end, each run's log-ratio interpolated linearly
    between its iterations (iterations of whole episodes vary in size: each point has every run)."""
    logs: dict[str, np.ndarray] = {}
    with np.errstate(divide="ignore", invalid="ignore"):
        ratios = {when: [np.log(np.divide(s[f"pevfa_{when}"], s[f"vfa_{when}"])) for s in series]
                  for when in ("before", "after")}  # fmt: skip
    if all("policy_id" in s for s in series):  # the snapshot k of every run: the same gradient step, the same env step
        keys = [[int(k) for k in s["policy_id"]] for s in series]
        end = min(max(ks) for ks in keys)
        grid = sorted({k for ks in keys for k in ks if k <= end})
        steps = np.nanmean([_on_grid(np.asarray(s["timesteps"], float), ks, grid) for s, ks in zip(series, keys)], 0)
        for when, values in ratios.items():
            logs[when] = np.array([_on_grid(v, ks, grid) for v, ks in zip(values, keys)])
    else:
        size = max(1.0, float(np.median(np.concatenate([np.diff([0.0, *s["timesteps"]]) for s in series]))))
        steps = np.arange(1, int(min(s["timesteps"][-1] for s in series) // size) + 1) * size
        for when, values in ratios.items():
            logs[when] = np.array([_interpolated(np.asarray(s["timesteps"], float), v, steps)
                                   for s, v in zip(series, values)])  # fmt: skip
    curves = {"steps": steps}
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)  # the mean of an all-NaN slice is NaN
        for when, per_run in logs.items():
            per_point = np.nanmean(per_run, axis=0)
            first = [i - window // 2 for i in range(len(steps))]  # each window: ``window`` points around i, cut at the ends
            curves[when] = np.exp([np.nanmean(per_point[max(0, f) : f + window]) for f in first])
    return curves


def _on_grid(values: np.ndarray, keys: list[int], grid: list[int]) -> np.ndarray:
    """A run's finite values at the grid's keys, averaged where several have one key (NaN where none)."""
    position = {k: i for i, k in enumerate(grid)}
    sums, counts = np.zeros(len(grid)), np.zeros(len(grid))
    for k, value in zip(keys, values):
        if k in position and np.isfinite(value):
            sums[position[k]] += value
            counts[position[k]] += 1
    return np.divide(sums, counts, out=np.full(len(grid), np.nan), where=counts > 0)


def _interpolated(steps: np.ndarray, values: np.ndarray, grid: np.ndarray) -> np.ndarray:
    """A run's finite values interpolated linearly at the grid's env steps (NaN outside its scored iterations)."""
    finite = np.isfinite(values)
    if not finite.any():
        return np.full(len(grid), np.nan)
    return np.interp(grid, steps[finite], values[finite], left=np.nan, right=np.nan)


def plot_local_generalization(runs: Runs, png: pathlib.Path, off_policy: bool = False) -> None:
    """One panel per task with diagnostic runs: PeVFA's error / the conventional critic's over training (before and
    after the iteration's critic update; ``off_policy``: the window's updates)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    panels = [(task, variant, diagnosed(variant_runs))
              for task, by_variant in runs.items() for variant, variant_runs in by_variant.items()]  # fmt: skip
    panels = [panel for panel in panels if panel[2]]
    figure, axes = plt.subplots(1, len(panels), figsize=(4.5 * len(panels), 3.4), squeeze=False)
    for ax, (task, variant, series) in zip(axes[0], panels):
        curves = local_generalization_curves(series)
        before = "before the window's updates" if off_policy else "before the critic update"
        ax.plot(curves["steps"] / 1e6, curves["before"], label=before)
        ax.plot(curves["steps"] / 1e6, curves["after"], "--", label="after")
        ax.axhline(1.0, color="grey", linewidth=0.8)
        ax.set(yscale="log", xlabel="env steps (M)", title=f"{task}, {variant} ({len(series)} runs)")
        ax.title.set_fontsize(9)
    axes[0][0].set_ylabel("PeVFA's error / conventional critic's")
    axes[0][0].legend(fontsize=7)
    figure.tight_layout()
    figure.savefig(png, dpi=80)
    plt.close(figure)


def mean_curve(variant_runs: list[dict]) -> dict[str, np.ndarray]:
    """The runs' evaluations over their common length: env steps, mean training CPU minutes, the mean return and half
    its std over the runs."""
    n = min(len(r["curve"]["mean"]) for r in variant_runs)
    means = np.array([r["curve"]["mean"][:n] for r in variant_runs])
    return {
        "steps": np.array(variant_runs[0]["curve"]["steps"][:n], float),
        "cpu_minutes": np.mean([r["curve"]["cpu_s"][:n] for r in variant_runs], axis=0) / 60,
        "mean": means.mean(0),
        "half_std": means.std(0) / 2,
    }


def draw_curves(axes, variant_runs: list[dict], color: str, label: str) -> None:
    """The runs' mean curve (± half a std) per env step on ``axes[0]``, per training CPU minute on ``axes[1]``."""
    curve = mean_curve(variant_runs)
    for ax, x in zip(axes, (curve["steps"] / 1e6, curve["cpu_minutes"])):
        ax.plot(x, curve["mean"], color=color, label=f"{label} ({len(variant_runs)})")
        ax.fill_between(x, curve["mean"] - curve["half_std"], curve["mean"] + curve["half_std"], color=color, alpha=0.2)


def label_columns(axes, column: int, task: str) -> None:
    """A task's column of curves: its title, the axes' names, the legend."""
    axes[0][column].set_title(task, fontsize=9)
    axes[0][column].set_xlabel("env steps (M)")
    axes[1][column].set_xlabel("training CPU minutes")
    axes[0][column].legend(fontsize=7)
    if column == 0:
        axes[0][0].set_ylabel("evaluation return (mean ± half std)")
        axes[1][0].set_ylabel("evaluation return (mean ± half std)")


def plot_beside(runs: Runs, other: Runs, baseline: str, labels: tuple[str, str], png: pathlib.Path) -> None:
    """The baseline's curves in two protocols' runs (``labels``), per env step and per CPU minute, a column per task
    that both ran."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    tasks = [t for t in table1_order(runs, other) if runs.get(t, {}).get(baseline) and other.get(t, {}).get(baseline)]
    if not tasks:
        return
    figure, axes = plt.subplots(2, len(tasks), figsize=(3.4 * len(tasks), 6.0), squeeze=False)
    for column, task in enumerate(tasks):
        for color, label, some in (("C0", labels[0], runs), ("C1", labels[1], other)):
            draw_curves((axes[0][column], axes[1][column]), some[task][baseline], color, f"{baseline}, {label}")
        label_columns(axes, column, task)
    figure.tight_layout()
    png.parent.mkdir(parents=True, exist_ok=True)
    figure.savefig(png, dpi=80)
    plt.close(figure)


def plot(runs, png: pathlib.Path, normalized: dict[str, aggregate.TaskScores]) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    tasks = list(runs)
    figure, axes = plt.subplots(2, len(tasks) + 1, figsize=(3.4 * (len(tasks) + 1), 6.0), squeeze=False)
    colors = {}
    compared = compared_variants(runs)  # the diagnostic's runs are slower by their extra critic
    for column, task in enumerate(tasks):
        for variant, variant_runs in runs[task].items():
            if variant not in compared:
                continue
            color = colors.setdefault(variant, f"C{len(colors)}")
            draw_curves((axes[0][column], axes[1][column]), variant_runs, color, variant)
        label_columns(axes, column, task)
    taus = np.linspace(0, 2.5, 101)
    ax = axes[0][-1]
    for variant, scores in normalized.items():
        low, high = aggregate.profile_band(scores, taus)
        ax.plot(taus, aggregate.performance_profile(scores, taus), color=colors.get(variant), label=variant)
        ax.fill_between(taus, low, high, color=colors.get(variant), alpha=0.2)
    ax.set_title("performance profile", fontsize=9)
    ax.set_xlabel("max average return / baseline's mean")
    ax.set_ylabel("fraction of runs above")
    if normalized:
        ax.legend(fontsize=7)
    else:  # no task where the baseline's mean is positive (the report says so)
        ax.text(0.5, 0.5, "no task to compare", ha="center", va="center", transform=ax.transAxes, fontsize=8)
    axes[1][-1].axis("off")
    figure.tight_layout()
    png.parent.mkdir(parents=True, exist_ok=True)
    figure.savefig(png, dpi=80)
    plt.close(figure)
