"""SB3's training logs of zoo runs: the parser of SB3's log tables (a zoo trial keeps them compactly) and what they say
after the peak (``benchmarks/training_logs.py``: why a return falls once it has peaked)."""

import contextlib
import json
import pathlib
import re

import numpy as np

#: Logged keys kept per iteration
KEYS = (
    "time/total_timesteps",
    "rollout/ep_rew_mean",
    "train/explained_variance",
    "train/value_loss",
    "train/approx_kl",
    "train/clip_fraction",
    "train/std",
    "pevfa/history_value_loss",
    "pevfa/embedding_norm",
    "pevfa/embedding_saturated_fraction",
    "pevfa/value_chi_gradient",
)
#: Training signals reported (the rest of :data:`KEYS` locates them)
SIGNALS = tuple(key for key in KEYS if key.startswith(("train/", "pevfa/")))
ROW = re.compile(r"^\|\s+(\S+)\s+\|\s+(\S*)\s+\|$")


def parse_log(text: str) -> dict[str, list[float]]:
    """SB3's human-readable log tables -> ``{key: [value per table]}`` for :data:`KEYS` (NaN where a table lacks one)."""
    tables, current, section, inside = [], {}, "", False
    for line in text.splitlines():
        if line.startswith("----"):
            if inside and current:
                tables.append(current)
            current, section, inside = {}, "", not inside
            continue
        match = ROW.match(line.strip())
        if not inside or match is None:
            continue
        name, value = match.groups()
        if name.endswith("/") and not value:
            section = name
        elif value:
            with contextlib.suppress(ValueError):  # e.g. a progress bar's text
                current[section + name] = float(value)
    tables = [table for table in tables if "time/total_timesteps" in table]
    return {key: [table.get(key, float("nan")) for table in tables] for key in KEYS}


def collect(out: pathlib.Path) -> None:
    """``<out>/logs/<run>.json`` from every ``<out>/runs/<run>/output.log`` (kept ones are not read again)."""
    (out / "logs").mkdir(exist_ok=True)
    for log in sorted(out.glob("runs/*/output.log")):
        target = out / "logs" / f"{log.parent.name}.json"
        if (out / f"{log.parent.name}.json").exists() and not target.exists():  # finished runs only
            target.write_text(json.dumps(parse_log(log.read_text(errors="replace"))))


def runs_of(out: pathlib.Path, env_id: str) -> dict[str, list[tuple[dict, dict]]]:
    """variant -> [(result, logs)] of the finished runs of ``env_id``."""
    found: dict[str, list[tuple[dict, dict]]] = {}
    for path in sorted(out.glob(f"{env_id}_*.json")):
        result = json.loads(path.read_text())
        logs_path = out / "logs" / path.name
        logs = json.loads(logs_path.read_text()) if logs_path.exists() else {}
        found.setdefault(result["variant"], []).append((result, logs))
    return found


def window_mean(logs: dict, key: str, low: float, high: float) -> float:
    """Mean of the finite values of ``key`` logged at env steps in ``(low, high]``, NaN if none."""
    steps, values = np.asarray(logs.get("time/total_timesteps", [])), np.asarray(logs.get(key, []), dtype=float)
    chosen = values[(steps > low) & (steps <= high)] if len(values) else values
    return float(np.nanmean(chosen)) if np.isfinite(chosen).any() else float("nan")


def finite_mean(values: list[float]) -> float:
    """Mean over runs of their finite values (a run whose peak is its last evaluation has no "after"), NaN if none."""
    finite = [value for value in values if np.isfinite(value)]
    return float(np.mean(finite)) if finite else float("nan")


def curve_stats(result: dict) -> dict[str, float]:
    """One run's evaluation curve: its peak (and where), its final return (the last three evaluations), the best mean
    of three consecutive evaluations (NaN under three), and over the curve's second half (NaN under four
    evaluations) the mean absolute change from one evaluation to the next and the standard error of one evaluation
    (``std / sqrt(episodes)``): a swing far above that error is the policy changing, not the evaluation's noise."""
    curve = result["curve"]
    returns, half = np.array([point["mean_return"] for point in curve]), len(curve) // 2
    late = result.get("episode_returns", [])[half:]  # each evaluation's episodes, where recorded
    errors = [np.std(episodes) / np.sqrt(len(episodes)) for episodes in late if len(episodes)]
    long_enough = len(returns) >= 4
    return {
        "peak": returns.max(),
        "peak_step": curve[int(returns.argmax())]["timesteps"],
        "final": returns[-3:].mean(),
        "smoothed": np.convolve(returns, np.ones(3) / 3, mode="valid").max() if len(returns) >= 3 else np.nan,
        "swing": np.abs(np.diff(returns[half:])).mean() if long_enough else np.nan,
        "error": np.mean(errors) if errors and long_enough else np.nan,
    }


def percent(ratio: float) -> str:
    """``ratio - 1`` as a signed whole percentage ("0 %" for what rounds to zero, NaN as "nan")."""
    if not np.isfinite(ratio):
        return "nan"
    change = round((ratio - 1) * 100)
    return f"{change:+d} %" if change else "0 %"


def report(out: pathlib.Path, env_id: str) -> str:
    """Markdown: the peak and the fall per variant, and each signal averaged before and after the peak."""
    lines = [
        f"**{env_id}**: peak and fall (mean over seeds; final = mean of the last three evaluations; smoothed peak = "
        "the best mean of three consecutive evaluations, over the runs with three; swing = the mean absolute change "
        "from one evaluation to the next over the second half of the run; eval s.e. = one evaluation's standard "
        "error there)",
        "",
        "| variant | seeds | peak | at step (mean) | final | fall | runs falling > 20 % "
        "| smoothed peak | fall from it | swing | eval s.e. |",
        "|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    phase_rows = []
    for variant, runs in runs_of(out, env_id).items():
        stats = [curve_stats(result) for result, _ in runs]
        before = {key: [] for key in SIGNALS}
        after = {key: [] for key in SIGNALS}
        for (_, logs), run in zip(runs, stats):
            for key in SIGNALS:
                before[key].append(window_mean(logs, key, 0, run["peak_step"]))
                after[key].append(window_mean(logs, key, run["peak_step"], np.inf))
        mean = {key: np.mean([run[key] for run in stats]) for key in ("peak", "peak_step", "final")}
        smoothed = [(run["smoothed"], run["final"]) for run in stats if np.isfinite(run["smoothed"])]
        smoothed_peak = np.mean([peak for peak, _ in smoothed]) if smoothed else np.nan
        smoothed_fall = np.mean([final for _, final in smoothed]) / smoothed_peak if smoothed else np.nan
        falls = sum(run["final"] < 0.8 * run["peak"] for run in stats)
        lines.append(
            f"| {variant} | {len(runs)} | {mean['peak']:.0f} | {mean['peak_step'] / 1000:.0f}k | {mean['final']:.0f} | "
            f"{percent(mean['final'] / mean['peak'])} | {falls} of {len(runs)} | {smoothed_peak:.0f} | "
            f"{percent(smoothed_fall)} | {finite_mean([run['swing'] for run in stats]):.0f} | "
            f"{finite_mean([run['error'] for run in stats]):.0f} |"
        )
        cells = [f"{finite_mean(before[key]):.3g} / {finite_mean(after[key]):.3g}" for key in SIGNALS]
        phase_rows.append(f"| {variant} | " + " | ".join(cells) + " |")
    lines += [
        "",
        "Training signals, mean before / after each run's peak (NaN: not logged by that variant):",
        "",
        *header(["variant"]),
        *phase_rows,
    ]
    return "\n".join(lines)


def header(first: list[str]) -> list[str]:
    """A markdown table's header: the ``first`` columns, then one per signal."""
    names = [*first, *(key.split("/")[1] for key in SIGNALS)]
    return ["| " + " | ".join(names) + " |", "|" + "---|" * len(names)]


def thousands(steps: int) -> str:
    """Env steps as "20k", "2.5k", "1M"."""
    return f"{steps / 1e6:g}M" if steps >= 1_000_000 else f"{steps / 1000:g}k"


def window_report(out: pathlib.Path, env_id: str, edges: list[int]) -> str:
    """Markdown: each signal (and the evaluations' mean return) per window of env steps ``(edges[i-1], edges[i]]``,
    mean over the seeds that reached ``edges[i]`` (NaN: no such seed, or not logged), one row per variant and window."""
    if not edges or min(edges) <= 0:
        raise ValueError(f"window edges must be positive env steps, got {edges}")
    edges = sorted(set(edges))
    lines = [
        f"**{env_id}**: training signals per window of env steps (mean over the seeds that reached its end; NaN: not logged)",
        "",
        *header(["variant", "steps", "seeds", "eval return"]),
    ]
    for variant, runs in runs_of(out, env_id).items():
        for low, high in zip([0, *edges], edges):
            reached = [(result, logs) for result, logs in runs if result["timesteps"] >= high]
            returns = [
                np.mean([p["mean_return"] for p in result["curve"] if low < p["timesteps"] <= high] or [np.nan])
                for result, _ in reached
            ]
            cells = [f"{finite_mean([window_mean(logs, key, low, high) for _, logs in reached]):.3g}" for key in SIGNALS]
            label = f"{thousands(low)}-{thousands(high)}"
            lines.append(f"| {variant} | {label} | {len(reached)} | {finite_mean(returns):.0f} | " + " | ".join(cells) + " |")
    return "\n".join(lines)


def interpolated(grid: np.ndarray, logs: dict, key: str) -> np.ndarray:
    """``key`` on ``grid`` from the iterations that logged it (evaluation tables log no training keys)."""
    steps, values = np.asarray(logs["time/total_timesteps"]), np.asarray(logs[key], dtype=float)
    finite = np.isfinite(values)
    return np.interp(grid, steps[finite], values[finite]) if finite.any() else np.full(len(grid), np.nan)


def plot(out: pathlib.Path, env_ids: list[str], path: pathlib.Path) -> None:
    """Per env (columns): the evaluation curve and the training signals (rows), mean over seeds per variant."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    keys = ["eval", "train/explained_variance", "train/value_loss", "pevfa/history_value_loss", "train/approx_kl",
            "train/std", "pevfa/embedding_saturated_fraction", "pevfa/value_chi_gradient"]  # fmt: skip
    figure, axes = plt.subplots(len(keys), len(env_ids), figsize=(6 * len(env_ids), 2.2 * len(keys)), squeeze=False)
    for column, env_id in enumerate(env_ids):
        for variant, runs in runs_of(out, env_id).items():
            for row, key in enumerate(keys):
                if key == "eval":
                    grid = np.array([point["timesteps"] for point in runs[0][0]["curve"]])
                    values = [[point["mean_return"] for point in result["curve"]] for result, _ in runs]
                else:
                    grid = np.linspace(10_000, runs[0][0]["timesteps"], 60)
                    values = [interpolated(grid, logs, key) for _, logs in runs if logs and key in logs]
                values = np.asarray(values, dtype=float)
                if values.size and np.isfinite(values).all(axis=0).any():
                    axes[row, column].plot(grid, values.mean(axis=0), label=variant)
                axes[row, column].set_ylabel(key.split("/")[-1], fontsize=8)
        axes[0, column].set_title(env_id)
        axes[-1, column].set_xlabel("env steps")
        for row in (2, 3):
            axes[row, column].set_yscale("log")
    axes[0, 0].legend(fontsize=7)
    figure.tight_layout()
    figure.savefig(path, dpi=90)
