"""The report of zoo runs (``benchmarks/learning.py --report``), read from their JSON records: Table-1 style markdown
per task with bootstrap CIs, the per-second views against the baseline, the aggregate over tasks, learning curves and
performance profiles."""

import json
import pathlib

import numpy as np

from . import aggregate
from .definitions import ZOO_VARIANTS
from .zoo import add_wall_clock, cpu_seconds


def load_results(out: pathlib.Path) -> dict[str, dict[str, list[dict]]]:
    """env -> variant -> runs (sorted by seed)."""
    results: dict[str, dict[str, list[dict]]] = {}
    for path in sorted(out.glob("*.json")):
        result = json.loads(path.read_text())
        folder = out / "runs" / path.stem
        if "wall_s" not in result["curve"][0] and folder.is_dir():  # runs of before the per-second view
            add_wall_clock(result, folder)
        results.setdefault(result["env"], {}).setdefault(result["variant"], []).append(result)
    for variants in results.values():
        for runs in variants.values():
            runs.sort(key=lambda r: r["seed"])
    return results


def scores(runs: list[dict]) -> dict[str, np.ndarray]:
    """Per-seed scores: max average return (the paper's), final average return, area under the curve (mean)."""
    curves = [np.array([c["mean_return"] for c in r["curve"]]) for r in runs]
    return {
        "max": np.array([c.max() for c in curves]),
        "final": np.array([c[-1] for c in curves]),
        "auc": np.array([c.mean() for c in curves]),
    }


def bootstrap_ci(values: np.ndarray, reps: int = 5000) -> tuple[float, float]:
    """Percentile bootstrap 95 % CI of the mean over seeds: rliable's stratified bootstrap for a single task.

    (scipy's, since rliable 1.2 does not run with today's arch/pandas: arch 7 fails to import under pandas 3 and
    arch 8 rejects rliable's ``random_state`` argument.)"""
    from scipy.stats import bootstrap

    if len(values) < 2:
        return float("nan"), float("nan")
    result = bootstrap((values,), np.mean, n_resamples=reps, method="percentile", rng=np.random.default_rng(0))
    return float(result.confidence_interval.low), float(result.confidence_interval.high)


def report(out: pathlib.Path, baseline: str = "ppo", paired: bool = False) -> str:
    """Table-1 style markdown per task: max average return +- half a std over seeds (as the paper), its rliable
    95 % CI, final return, area under the curve, the change of the mean vs PPO, seeds and wall time."""
    lines = []
    results = load_results(out)
    for env_id, variants in sorted(results.items()):
        base = scores(variants[baseline])["max"].mean() if baseline in variants else None
        lines += [
            f"**{env_id}** ({variants[next(iter(variants))][0]['timesteps']:,} steps)",
            "",
            f"| variant | seeds | max avg return (± ½ std) | 95 % CI (bootstrap) | vs {baseline} | final avg return | "
            "area under curve | max per seed | wall time / run |",
            "|---|---|---|---|---|---|---|---|---|",
        ]
        for variant, runs in sorted(variants.items(), key=lambda item: (item[0] != baseline, item[0])):
            s = scores(runs)
            low, high = bootstrap_ci(s["max"])
            change = "" if base is None or variant == baseline else f"{s['max'].mean() / base - 1:+.0%}"
            lines.append(
                f"| {variant} | {len(runs)} | {s['max'].mean():.0f} ± {s['max'].std() / 2:.0f} | [{low:.0f}, {high:.0f}] | "
                f"{change} | {s['final'].mean():.0f} ± {s['final'].std() / 2:.0f} | {s['auc'].mean():.0f} | "
                f"{', '.join(f'{v:.0f}' for v in s['max'])} | {np.mean([r['wall_time_s'] for r in runs]):.0f} s |"
            )
        lines += ["", *per_second(variants, baseline, paired), ""]
    return "\n".join(lines + aggregate_table(results, baseline, paired))


def task_scores(results: dict[str, dict[str, list[dict]]], baseline: str, paired: bool = False) -> dict[str, dict[str, dict]]:
    """view -> variant -> task -> per-seed scores, for the variants run on every task that has the baseline: the
    max average return (per step) and the best-so-far return at the baseline's mean wall-clock time (per second;
    ``paired``: at the time of the baseline run of the same seed, :func:`paired_runs`)."""
    tasks = {env_id: variants for env_id, variants in results.items() if baseline in variants}
    common = set.intersection(*(set(variants) for variants in tasks.values())) if tasks else set()
    views: dict[str, dict[str, dict]] = {
        "max average return (per step)": {},
        "best-so-far at the baseline's time": {},
        "best-so-far at the baseline's CPU time": {},
    }
    for env_id, variants in tasks.items():
        for variant in common:
            runs = variants[variant]
            views["max average return (per step)"].setdefault(variant, {})[env_id] = scores(runs)["max"]
            pairs = paired_runs(runs, variants[baseline], paired)
            if pairs and "wall_s" in runs[0]["curve"][0]:
                best = np.array([best_so_far_at(r, budgets(base)["wall"]) for r, base in pairs])
                views["best-so-far at the baseline's time"].setdefault(variant, {})[env_id] = best
            if pairs and all("cpu_time_s" in r for r in runs + variants[baseline]):
                best = np.array([best_so_far_at(r, budgets(base)["cpu"], "cpu") for r, base in pairs])
                views["best-so-far at the baseline's CPU time"].setdefault(variant, {})[env_id] = best
    return {view: variants for view, variants in views.items() if variants or view.endswith("(per step)")}


def aggregate_table(results: dict[str, dict[str, list[dict]]], baseline: str, paired: bool = False) -> list[str]:
    """The aggregate over tasks (``aggregate``): IQM and mean of the scores normalised by the baseline's
    mean per task, with 95 % stratified bootstrap CIs over tasks and seeds."""
    views = task_scores(results, baseline, paired)
    if not views["max average return (per step)"]:
        return []
    tasks = sorted(views["max average return (per step)"][baseline])
    lines = [
        f"**Aggregate over {len(tasks)} task(s)** ({', '.join(tasks)}; each run's score / {baseline}'s mean on its task; "
        "IQM and mean with 95 % stratified bootstrap CIs):",
        "",
        "| view | variant | runs | IQM [95 % CI] | mean [95 % CI] |",
        "|---|---|---|---|---|",
    ]
    for view, variants in views.items():
        for variant, raw in sorted(variants.items(), key=lambda item: (item[0] != baseline, item[0])):
            normalized = aggregate.normalized(raw, variants[baseline])
            iqm_low, iqm_high = aggregate.stratified_bootstrap_ci(normalized, aggregate.iqm)
            mean_low, mean_high = aggregate.stratified_bootstrap_ci(normalized, aggregate.mean)
            lines.append(
                f"| {view} | {variant} | {sum(len(v) for v in raw.values())} | {aggregate.iqm(normalized):.2f} "
                f"[{iqm_low:.2f}, {iqm_high:.2f}] | {aggregate.mean(normalized):.2f} [{mean_low:.2f}, {mean_high:.2f}] |"
            )
    return [*lines, ""]


def plot_profiles(out: pathlib.Path, png: pathlib.Path, baseline: str, paired: bool = False) -> None:
    """Performance profiles of both views (fraction of runs above tau, baseline-normalised, with 95 % bands)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    views = task_scores(load_results(out), baseline, paired)
    fig, axes = plt.subplots(1, len(views), figsize=(6 * len(views), 4), squeeze=False)
    taus = np.linspace(0.0, 2.0, 81)
    for ax, (view, variants) in zip(axes[0], views.items()):
        for variant, raw in sorted(variants.items()):
            normalized = aggregate.normalized(raw, variants[baseline])
            low, high = aggregate.profile_band(normalized, taus)
            ax.plot(taus, aggregate.performance_profile(normalized, taus), label=variant)
            ax.fill_between(taus, low, high, alpha=0.2)
        ax.set(title=f"{view}, {', '.join(sorted(next(iter(variants.values()), {})))}", xlabel=f"score / {baseline}'s mean",
               ylabel="fraction of runs > tau")  # fmt: skip
        ax.legend()
    fig.tight_layout()
    fig.savefig(png, dpi=100)


def best_so_far_at(run: dict, seconds: float, clock: str = "wall") -> float:
    """The best evaluation of ``run`` made within ``seconds`` of its start (``clock``: ``"wall"``-clock or ``"cpu"``
    seconds of the training process; -inf if none)."""
    times = [c["wall_s"] if clock == "wall" else cpu_seconds(run, c) for c in run["curve"]]
    return aggregate.best_within([c["mean_return"] for c in run["curve"]], times, seconds, float("-inf"))


def budgets(baseline_runs: list[dict]) -> dict[str, float]:
    """The baseline's mean wall-clock and CPU seconds of a whole run."""
    return {
        "wall": float(np.mean([r["curve"][-1].get("wall_s", np.inf) for r in baseline_runs])),
        "cpu": float(np.mean([r.get("cpu_time_s", np.inf) for r in baseline_runs])),
    }


def paired_runs(runs: list[dict], baseline_runs: list[dict], paired: bool) -> list[tuple[dict, list[dict]]]:
    """Each run with the baseline runs that set its budget: all of them, or (``paired``) the one of its seed, which
    ran beside it on the same machine (runs of a seed the baseline lacks are left out). Pairs keep the per-second
    view true when invocations ran on machines of different speeds."""
    if not paired:
        return [(run, baseline_runs) for run in runs]
    by_seed = {r["seed"]: r for r in baseline_runs}
    return [(run, [by_seed[run["seed"]]]) for run in runs if run["seed"] in by_seed]


def per_second(variants: dict[str, list[dict]], baseline: str, paired: bool = False) -> list[str]:
    """The same runs per second: speed (steps per wall-clock and per CPU second of the training process) and the
    best-so-far return at the baseline's own mean wall-clock time of a whole run; ``paired``: speed as the mean
    ratio to the baseline run of the same seed, and that run's time as the budget (:func:`paired_runs`)."""
    if baseline not in variants or "wall_s" not in variants[baseline][0]["curve"][0]:
        return []
    budget = budgets(variants[baseline])
    has_cpu = all("cpu_time_s" in r for runs in variants.values() for r in runs)
    clocks = ("wall", "cpu") if has_cpu else ("wall",)
    if paired:
        title = f"Per second, each seed against the {baseline} run of its seed (its whole run's time the budget"
        at = "at the paired run's time"
        columns = [f"best-so-far {at} (± ½ std) | per seed |", f"best-so-far {at}, CPU (± ½ std) | per seed |"]
    else:
        title = f"Per second (budgets: {baseline}'s mean run, {budget['wall']:.0f} s wall-clock" + (
            f", {budget['cpu']:.0f} CPU-s" if has_cpu else ""
        )
        columns = [f"best-so-far at {budget['wall']:.0f} s (± ½ std) | per seed |",
                   f"best-so-far at {budget['cpu']:.0f} CPU-s (± ½ std) | per seed |"]  # fmt: skip
    lines = [
        title + ("; an evaluation's CPU time is its run's, prorated by steps):" if has_cpu else "):"),
        "",
        f"| variant | steps/s (wall) | steps/CPU-s | speed vs {baseline} (wall / CPU) | " + " ".join(columns[: len(clocks)]),
        "|---|---|---|---|---|---|" + ("---|---|" if has_cpu else ""),
    ]
    for variant, runs in sorted(variants.items(), key=lambda item: (item[0] != baseline, item[0])):
        pairs = paired_runs(runs, variants[baseline], paired)
        if not pairs:
            continue
        runs = [run for run, _ in pairs]
        speed = np.array([speed_of(r, "wall") for r in runs])
        cpu = np.mean([speed_of(r, "cpu") for r in runs]) if has_cpu else np.nan
        ratio = {
            clock: np.mean([speed_of(run, clock) / np.mean([speed_of(b, clock) for b in base]) for run, base in pairs])
            for clock in clocks
        }
        row = f"| {variant} | {speed.mean():.0f} ± {speed.std():.0f} | "
        row += f"{cpu:.0f} | " if has_cpu else "not recorded | "
        row += f"{ratio['wall']:.2f}x / " + (f"{ratio['cpu']:.2f}x | " if has_cpu else "- | ")
        for clock in clocks:
            best = np.array([best_so_far_at(r, budgets(base)[clock], clock) for r, base in pairs])
            row += f"{best.mean():.0f} ± {best.std() / 2:.0f} | {', '.join(f'{v:.0f}' for v in best)} | "
        lines.append(row.rstrip())
    return lines


def speed_of(run: dict, clock: str) -> float:
    """Environment steps per second of a whole run, by ``"wall"``-clock or by the training process's ``"cpu"`` time."""
    return run["timesteps"] / run["wall_time_s" if clock == "wall" else "cpu_time_s"]


def plot(out: pathlib.Path, png: pathlib.Path) -> None:
    """Learning curves per task, against environment steps (top), wall-clock seconds and CPU seconds of the training
    process (bottom; prorated by steps, :func:`cpu_seconds`): mean over seeds with a band of one std, every variant
    in its fixed colour."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    results = load_results(out)
    fig, axes = plt.subplots(3, len(results), figsize=(6 * len(results), 12), squeeze=False)
    palette = plt.get_cmap("tab20").colors  # more variants than the ten default colours: none shares one
    colors = {variant: palette[(2 * i) % 20 + (2 * i) // 20 % 2] for i, variant in enumerate(ZOO_VARIANTS)}
    for column, (env_id, variants) in enumerate(sorted(results.items())):
        for variant, runs in sorted(variants.items()):
            n = min(len(r["curve"]) for r in runs)
            returns = np.array([[c["mean_return"] for c in r["curve"][:n]] for r in runs])
            mean, std = returns.mean(axis=0), returns.std(axis=0)
            clocks = {
                "timesteps": lambda r, c: c["timesteps"],
                "wall_s": lambda r, c: c["wall_s"],
                "cpu_time_s": lambda r, c: cpu_seconds(r, c),
            }
            for row, (key, at) in enumerate(clocks.items()):
                if key not in runs[0]["curve"][0] and key not in runs[0]:
                    continue
                x = np.mean([[at(r, c) for c in r["curve"][:n]] for r in runs], axis=0)  # seeds' mean time per point
                ax = axes[row, column]
                ax.plot(x, mean, color=colors.get(variant), label=f"{variant} ({len(runs)} seeds)")
                ax.fill_between(x, mean - std, mean + std, color=colors.get(variant), alpha=0.2)
        axes[0, column].set(title=env_id, xlabel="environment steps", ylabel="average return (deterministic)")
        axes[1, column].set(title=env_id, xlabel="wall-clock seconds (mean over seeds)", ylabel="average return")
        axes[2, column].set(title=env_id, xlabel="CPU seconds of the training process (mean over seeds)",
                            ylabel="average return")  # fmt: skip
        axes[0, column].legend()
    fig.tight_layout()
    fig.savefig(png, dpi=100)
