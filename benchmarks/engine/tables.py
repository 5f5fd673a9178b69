"""The report's tables, from the runs that ``results.collect`` reads: Table 1's layout beside the paper's values, the
aggregates over tasks (IQM with CIs, probability of improvement), the target, the speed, the local-generalization
diagnostic and the training signals of zoo runs."""

from typing import Any

import numpy as np

from . import aggregate
from .definitions import is_diagnostic
from .results import Runs

#: The paper's Table 1 (2M steps, 4M for Ant; 10 seeds; mean, half a std): task -> variant -> (mean, half std)
PAPER_TABLE1: dict[str, dict[str, tuple[float, float]]] = {
    "HalfCheetah-v5": {"ppo": (2621, 259.31), "random": (2470, 291.65), "opr-e2e": (3171, 427.63),
                       "opr-cl": (3725, 348.55), "spr-e2e": (2774, 233.39)},
    "Hopper-v5": {"ppo": (1639, 294.47), "random": (1226, 348.10), "opr-e2e": (2085, 310.91),
                  "opr-cl": (2351, 231.11), "spr-e2e": (2227, 297.35)},
    "Walker2d-v5": {"ppo": (1505, 320.55), "random": (1269, 209.61), "opr-e2e": (1856, 305.51),
                    "opr-cl": (2038, 315.51), "spr-e2e": (1930.57, 456.02)},
    "Ant-v5": {"ppo": (2835, 152.04), "random": (2742, 71.11), "opr-e2e": (3581, 185.43),
               "opr-cl": (4019, 162.47), "spr-e2e": (3173, 184.75)},
    "InvertedDoublePendulum-v5": {"ppo": (9344, 11.02), "random": (9355, 0.40), "opr-e2e": (9357, 0.29),
                                  "opr-cl": (9355, 0.64), "spr-e2e": (9355, 0.89)},
    "LunarLanderContinuous-v3": {"ppo": (219, 5.33), "random": (226, 2.83), "opr-e2e": (238, 3.37),
                                 "opr-cl": (239, 3.70), "spr-e2e": (236, 3.13)},
}  # fmt: skip
#: The reproduction's target, for the paper's OPR-E2E: above the baseline's mean on at least 5 of Table 1's 6 tasks,
#: and an IQM of the baseline-normalized max average return of at least 1.15 whose 95 % CI's lower bound is above 1.0
TARGET = {"variant": "opr-e2e", "tasks": 5, "of": "Table 1's 6 tasks", "iqm": 1.15, "low": 1.0, "speed": None}
#: The target of each protocol that has one (the keys of ``TARGET``; ``low`` or ``speed`` None: no such bound). SAC:
#: SACPeVFA (OPR) above SAC on both tasks, an IQM of at least 1.1, at 0.7x SAC's env steps per CPU-second or more
TARGETS = {
    "paper": TARGET,
    "authors": TARGET,
    "sac": {"variant": "opr", "tasks": 2, "of": "its 2 tasks", "iqm": 1.1, "low": None, "speed": 0.7},
}
#: Means within this fraction of the baseline's are a tie, not above (InvertedDoublePendulum's ceiling of 9360)
TIE = 0.005
#: Column order of the variants
ORDER = (
    "ppo",
    "random",
    "opr-e2e",
    "opr-cl",
    "spr-e2e",
    "opr-e2e-default-schedule",
    "fingerprint-e2e",
    "opr",
    "spr",
    "fingerprint",
)
#: Training signals of the zoo protocol's SB3 logs: key -> column heading
SIGNALS = {
    "train/explained_variance": "explained variance",
    "pevfa/history_value_loss": "critic loss on history",
    "pevfa/value_chi_gradient": "\\|dV/dchi\\|",
    "pevfa/embedding_norm": "\\|chi\\|",
    "pevfa/embedding_saturated_fraction": "saturated chi units",
}


def best_so_far_at(run: dict[str, Any], cpu: float) -> float:
    """The run's best evaluation among those made within ``cpu`` seconds of training CPU (nan before its first)."""
    return aggregate.best_within(run["curve"]["mean"], run["curve"]["cpu_s"], cpu)


def probability_of_improvement(x: aggregate.TaskScores, y: aggregate.TaskScores) -> float:
    """P(X > Y) (ties count a half) over all pairs of runs of a task, averaged over tasks (rliable's)."""
    values = []
    for task in x:
        a, b = np.asarray(x[task])[:, None], np.asarray(y[task])[None, :]
        values.append(float(np.mean((a > b) + 0.5 * (a == b))))
    return float(np.mean(values))


def _cell(values: np.ndarray) -> str:
    return f"{values.mean():.0f} ± {values.std() / 2:.0f} ({len(values)})"  # half the std over seeds (ddof 0)


def ordered_variants(runs: Runs) -> list[str]:
    """The variants of the runs, in Table 1's column order."""
    present = {v for by_variant in runs.values() for v in by_variant}
    return sorted(present, key=lambda v: (ORDER.index(v.split(":")[-1]) if v.split(":")[-1] in ORDER else len(ORDER), v))


def compared_variants(runs: Runs) -> list[str]:
    """The variants that the aggregates, the speed and the curves compare: all but the diagnostic's,
    whose runs train an extra critic (their time) and draw other random numbers (their returns: in the table only)."""
    return [v for v in ordered_variants(runs) if not is_diagnostic(v)]


def table(runs: Runs, baseline: str, paper: bool) -> list[str]:
    variants = ordered_variants(runs)
    lines = [
        "| task | " + " | ".join(variants) + (" | paper: " + " / ".join(PAPER_TABLE1["Hopper-v5"]) if paper else "") + " |"
    ]
    lines.append("|---" * (len(variants) + 1 + paper) + "|")
    for task, by_variant in runs.items():
        base = np.mean([r["max_average_return"] for r in by_variant.get(baseline, [])] or [np.nan])
        cells = []
        for variant in variants:
            scores = np.array([r["max_average_return"] for r in by_variant.get(variant, [])])
            ratio = f" **{scores.mean() / base:.2f}x**" if len(scores) and variant != baseline and base > 0 else ""
            cells.append(_cell(scores) + ratio if len(scores) else "—")
        row = f"| {task} | " + " | ".join(cells)
        if paper:
            published = PAPER_TABLE1.get(task, {})
            ppo = published.get("ppo", (np.nan,))[0]
            row += " | " + " / ".join(
                f"{m:.0f} ({m / ppo:.2f}x)" if v != "ppo" else f"{m:.0f}" for v, (m, _) in published.items()
            )
        lines.append(row + " |")
    return lines


def comparable(runs: Runs, baseline: str, variant: str) -> list[str]:
    """The tasks where the variant and the baseline both have runs and the baseline's mean max average return is
    positive: a ratio to a mean at or below zero would reverse or lose the order of the scores."""
    return [
        t
        for t, by_variant in runs.items()
        if by_variant.get(variant)
        and by_variant.get(baseline)
        and np.mean([r["max_average_return"] for r in by_variant[baseline]]) > 0
    ]


def aggregates(runs: Runs, baseline: str) -> tuple[list[str], dict[str, aggregate.TaskScores]]:
    """IQM with CIs, probability of improvement, over the tasks where the baseline and the variant both have runs: per
    env step (max average return) and per CPU-second (best return within the baseline's mean CPU time of a run)."""
    lines = [f"| variant | tasks | runs | IQM of max average return / {baseline}'s mean [95 % CI] | P(variant > "
             f"{baseline}) | the same at {baseline}'s CPU time: IQM [95 % CI], P |", "|---|---|---|---|---|---|"]  # fmt: skip
    normalized: dict[str, aggregate.TaskScores] = {}
    for variant in compared_variants(runs):
        tasks = comparable(runs, baseline, variant)
        if not tasks:
            continue
        cells = []
        for score in (lambda r, base_runs: r["max_average_return"], at_baseline_cpu):
            scores = {t: np.array([score(r, runs[t][baseline]) for r in runs[t][variant]]) for t in tasks}
            base = {t: np.array([score(r, runs[t][baseline]) for r in runs[t][baseline]]) for t in tasks}
            if any(np.isnan(v).any() for v in (*scores.values(), *base.values())):  # a run without an evaluation then
                cells += ["— (a run has no evaluation in that time)", "—"]
                continue
            scaled = aggregate.normalized(scores, base)
            normalized.setdefault(variant, scaled)  # the performance profile's: per env step
            low, high = aggregate.normalized_bootstrap_ci(scores, base)
            value = aggregate.iqm(scaled)
            improvement = "—" if variant == baseline else f"{probability_of_improvement(scores, base):.2f}"
            cells += [f"{value:.2f} [{low:.2f}, {high:.2f}]", improvement]
        n = sum(len(runs[t][variant]) for t in tasks)
        lines.append(f"| {variant} | {len(tasks)} | {n} | {cells[0]} | {cells[1]} | {cells[2]}, {cells[3]} |")
    return lines, normalized


def table1_order(*runs: Runs) -> list[str]:
    """The tasks of the runs in Table 1's order, then the others in the runs' order."""
    order = list(PAPER_TABLE1)
    tasks = dict.fromkeys(task for some in runs for task in some)
    return sorted(tasks, key=lambda t: order.index(t) if t in order else len(order))


def beside(runs: Runs, other: Runs, baseline: str, labels: tuple[str, str]) -> list[str]:
    """Per task, each variant's ratio of mean max average return to the baseline's in two protocols' runs (``labels``:
    their names), and the paper's Table 1 where it has the variant."""
    variants = [v for v in compared_variants(runs) if v != baseline and v in compared_variants(other)]
    if not variants:
        return [f"No variant but {baseline} in both protocols' runs."]

    def ratio(by_variant: dict[str, list[dict[str, Any]]], variant: str) -> str:
        scores, base = ([r["max_average_return"] for r in by_variant.get(v, [])] for v in (variant, baseline))
        if not scores or not base or np.mean(base) <= 0:
            return "—"
        return f"{np.mean(scores) / np.mean(base):.2f}x ({len(scores)}/{len(base)})"

    lines = ["| task | " + " | ".join(f"{v}: {labels[0]} / {labels[1]} / the paper" for v in variants) + " |"]
    lines.append("|---" * (len(variants) + 1) + "|")
    for task in table1_order(runs, other):
        cells = []
        for variant in variants:
            published = PAPER_TABLE1.get(task, {})
            paper = f"{published[variant][0] / published[baseline][0]:.2f}x" if {variant, baseline} <= set(published) else "—"
            cells.append(f"{ratio(runs.get(task, {}), variant)} / {ratio(other.get(task, {}), variant)} / {paper}")
        lines.append(f"| {task} | " + " | ".join(cells) + " |")
    return lines


def baseline_beside(runs: Runs, other: Runs, baseline: str, labels: tuple[str, str], steps: int) -> list[str]:
    """Per task, the baseline's best evaluation within ``steps`` env steps and over its whole run (mean ± half std over
    seeds, runs in brackets) and its CPU minutes per run, in two protocols' runs (``labels``: their names)."""

    def cells(variant_runs: list[dict[str, Any]]) -> str:
        if not variant_runs:
            return "— | —"
        early = np.array([aggregate.best_within(r["curve"]["mean"], r["curve"]["steps"], steps) for r in variant_runs])
        whole = np.array([r["max_average_return"] for r in variant_runs])
        minutes = np.mean([r["cpu_seconds"] for r in variant_runs]) / 60
        return f"{_cell(early)} | {_cell(whole)}, {minutes:.0f} CPU-min"

    head = " | ".join(f"{label}: by {steps:,} steps | {label}: whole run" for label in labels)
    lines = [f"| task | {head} |", "|---" * 5 + "|"]
    for task in table1_order(runs, other):
        both = (r.get(task, {}).get(baseline, []) for r in (runs, other))
        lines.append(f"| {task} | " + " | ".join(cells(variant_runs) for variant_runs in both) + " |")
    return lines


def target_wording(spec: dict[str, Any], baseline: str) -> str:
    """What a target (``TARGETS``) asks, in the report's words."""
    bounds = f" with the CI's lower bound above {spec['low']}" if spec["low"] is not None else ""
    bounds += f", at {spec['speed']}x {baseline}'s env steps per CPU-second or more" if spec["speed"] else ""
    return (f"above {baseline}'s mean on at least {spec['tasks']} of {spec['of']}, IQM at least {spec['iqm']}"
            + bounds)  # fmt: skip


def target(runs: Runs, baseline: str, planned: dict[str, int], spec: dict[str, Any] = TARGET) -> list[str]:
    """The target (``spec``, one of ``TARGETS``) read from the runs of its variant: the tasks above the baseline's mean
    (by more than ``TIE``), the IQM with its CI (as in ``aggregates``), the median over its runs of their steps per
    CPU-second as a ratio to the baseline's (same machine) where the target bounds it, and met, or missed by how much;
    provisional while the variant or the baseline has fewer runs than ``planned`` (variant -> runs in its campaigns'
    grids; the report's, where every campaign is of one protocol, so that no variant name carries a protocol)."""
    variant = spec["variant"]
    tasks = comparable(runs, baseline, variant) if variant != baseline else []
    if not tasks:
        return []
    scores = {t: np.array([r["max_average_return"] for r in runs[t][variant]]) for t in tasks}
    base = {t: np.array([r["max_average_return"] for r in runs[t][baseline]]) for t in tasks}
    margin = {t: (scores[t].mean() - base[t].mean()) / abs(base[t].mean()) for t in tasks}
    ratio = {t: f"{t} {scores[t].mean() / base[t].mean():.2f}x" for t in tasks}
    tied = [ratio[t] for t in tasks if abs(margin[t]) <= TIE]
    below = [ratio[t] for t in tasks if margin[t] < -TIE]
    above = len(tasks) - len(tied) - len(below)
    value = aggregate.iqm(aggregate.normalized(scores, base))
    low, high = aggregate.normalized_bootstrap_ci(scores, base)
    short = [f"{spec['tasks'] - above} task(s)"] if above < spec["tasks"] else []
    short += [f"{spec['iqm'] - value:.3f} of IQM"] if value < spec["iqm"] else []
    short += [f"{spec['low'] - low:.3f} of the lower bound"] if spec["low"] is not None and low <= spec["low"] else []
    speed = ""
    if spec["speed"]:
        ratios = [speed_ratio(run, runs[t][baseline], "steps_per_cpu_second") for t in tasks for run in runs[t][variant]]
        speed = f", {np.median(ratios):.2f}x {baseline}'s steps per CPU-second (median of {len(ratios)} runs)"
        short += [f"{spec['speed'] - np.median(ratios):.2f}x of speed"] if np.median(ratios) < spec["speed"] else []
    made = {v: sum(len(by_variant.get(v, [])) for by_variant in runs.values()) for v in (variant, baseline)}
    missing = {v: planned.get(v, 0) - made[v] for v in made if made[v] < planned.get(v, 0)}
    apart = "; ".join(f"{word} on {', '.join(named)}" for word, named in (("tied", tied), ("below", below)) if named)
    return [
        f"- {variant}: above {baseline} on {above} of {len(tasks)} tasks"
        + (f" ({apart})" if apart else "")
        + f", IQM {value:.2f} [{low:.2f}, {high:.2f}]{speed}: "
        + ("met" if not short else "missed by " + ", ".join(short))
        + (f"; provisional, runs to come: {', '.join(f'{n} of {v}' for v, n in missing.items())}" if missing else "")
    ]


def same_machine(run: dict[str, Any], base_runs: list[dict[str, Any]]) -> list[dict[str, Any]]:
    """The baseline runs made on the machine (the boot) that made ``run``, or all of them where none was."""
    boot = run.get("worker", {}).get("boot_id")
    return [b for b in base_runs if boot and b.get("worker", {}).get("boot_id") == boot] or base_runs


def speed_ratio(run: dict[str, Any], base_runs: list[dict[str, Any]], key: str) -> float:
    """The run's speed (``key``: steps per CPU- or wall-second) over the mean of the baseline's on its machine."""
    return run[key] / float(np.mean([b[key] for b in same_machine(run, base_runs)]))


def at_baseline_cpu(run: dict[str, Any], base_runs: list[dict[str, Any]]) -> float:
    """The run's best evaluation within the mean training CPU time of the baseline's runs on its machine."""
    return best_so_far_at(run, float(np.mean([b["cpu_seconds"] for b in same_machine(run, base_runs)])))


def _mean(values: list[float]) -> float:
    return float(np.mean(values)) if values else np.nan


def per_step(variant_runs: list[dict[str, Any]], base_runs: list[dict[str, Any]]) -> float:
    """The variant's mean max average return over the baseline's (nan where either has no run or the baseline's mean
    is not positive)."""
    base = _mean([r["max_average_return"] for r in base_runs])
    return _mean([r["max_average_return"] for r in variant_runs]) / base if base > 0 else np.nan


def against_baseline(variant_runs: list[dict[str, Any]], base_runs: list[dict[str, Any]]) -> dict[str, float]:
    """The variant's runs over the baseline's on one task: ``per_step`` (mean max average return over the baseline's
    mean), ``cpu_speed`` and ``wall_speed`` (mean of each run's steps per CPU- and wall-second over the baseline's mean
    on its machine), ``at_cpu`` (mean best return within the baseline's mean CPU time, over the baseline's own, nan
    where not positive) and ``minutes`` (its mean CPU minutes per run)."""
    base_best = _mean([at_baseline_cpu(r, base_runs) for r in base_runs])
    best = _mean([at_baseline_cpu(r, base_runs) for r in variant_runs])
    return {
        "per_step": per_step(variant_runs, base_runs),
        "cpu_speed": _mean([speed_ratio(r, base_runs, "steps_per_cpu_second") for r in variant_runs]),
        "wall_speed": _mean([speed_ratio(r, base_runs, "steps_per_wall_second") for r in variant_runs]),
        "at_cpu": best / base_best if np.isfinite(best) and base_best > 0 else np.nan,
        "minutes": _mean([r["cpu_seconds"] for r in variant_runs]) / 60,
    }


def _times(value: float) -> str:
    return f"{value:.2f}x" if np.isfinite(value) else "—"


def speed(runs: Runs, baseline: str) -> list[str]:
    """Per task: the baseline's steps per CPU-second (wall-clock) and CPU minutes per run; per other variant, its
    speed per CPU-second (wall-clock) and best-so-far return within the baseline's mean CPU time, as ratios to the
    baseline's runs on the same machine where there are any (a campaign spans machines), and its CPU minutes."""
    variants = [v for v in compared_variants(runs) if v != baseline]
    lines = [f"| task | {baseline} | " + " | ".join(variants) + " |",
             "|---" * (len(variants) + 2) + "|"]  # fmt: skip
    for task, by_variant in runs.items():
        base_runs = by_variant.get(baseline, [])
        base_cpu = _mean([r["cpu_seconds"] for r in base_runs])
        base_speed = _mean([r["steps_per_cpu_second"] for r in base_runs])
        base_wall = _mean([r["steps_per_wall_second"] for r in base_runs])
        cells = [f"{base_speed:.0f} ({base_wall:.0f}), {base_cpu / 60:.0f}" if base_runs else "—"]
        for variant in variants:
            variant_runs = by_variant.get(variant, [])
            if not variant_runs or not base_runs:
                cells.append("—")
                continue
            r = against_baseline(variant_runs, base_runs)
            cells.append(f"{r['cpu_speed']:.2f}x ({r['wall_speed']:.2f}x), {_times(r['at_cpu'])}, {r['minutes']:.0f}")
        lines.append(f"| {task} | " + " | ".join(cells) + " |")
    return lines


def compact(runs: Runs, baseline: str, variant: str, other: Runs | None = None, label: str = "other protocol") -> list[str]:
    """A results page's table: per task the baseline's and the variant's max average return (mean ± half std over
    seeds, runs in brackets), the variant's ratios to the baseline per env step, at the baseline's CPU time and in
    steps per CPU-second; per env step in ``other`` runs (another protocol's, ``label``) and in the paper's Table 1
    where it has the variant."""
    tasks = table1_order(runs, other or {})
    published = any(variant in PAPER_TABLE1.get(t, {}) for t in tasks)
    head = [baseline, variant, "per step", f"at {baseline}'s CPU time", "speed"]
    head += [f"{label}, per step"] if other is not None else []
    head += ["the paper, per step"] if published else []
    lines = ["| task | " + " | ".join(head) + " |", "|---" * (len(head) + 1) + "|"]
    for task in tasks:
        by_variant = runs.get(task, {})
        base_runs, variant_runs = by_variant.get(baseline, []), by_variant.get(variant, [])
        cells = [_cell(np.array([r["max_average_return"] for r in rs])) if rs else "—" for rs in (base_runs, variant_runs)]
        if base_runs and variant_runs:
            r = against_baseline(variant_runs, base_runs)
            cells += [_times(r["per_step"]), _times(r["at_cpu"]), _times(r["cpu_speed"])]
        else:
            cells += ["—"] * 3
        if other is not None:
            theirs = other.get(task, {})
            cells.append(_times(per_step(theirs.get(variant, []), theirs.get(baseline, []))))
        if published:
            paper = PAPER_TABLE1.get(task, {})
            cells.append(_times(paper[variant][0] / paper[baseline][0]) if {variant, baseline} <= set(paper) else "—")
        lines.append(f"| {task} | " + " | ".join(cells) + " |")
    return lines


def diagnosed(variant_runs: list[dict[str, Any]]) -> list[dict[str, list[float]]]:
    """The diagnostic's series of the runs that have one (a run that went on from a checkpoint went on with its
    conventional critic: its series lacks only what was not scored when the checkpoint was taken)."""
    return [r["local_generalization"] for r in variant_runs if r.get("local_generalization")]


def local_generalization(runs: Runs, unit: str = "iterations") -> list[str]:
    """Per task and variant with the diagnostic: the PeVFA's and the conventional critic's errors against the
    Monte-Carlo returns of each new policy before and after the iteration's critic update (paper Fig. 3b / 8; off
    policy: per window between two snapshots, ``unit`` "windows"), over the runs of ``diagnosed``; per run, its seed,
    its best return and its median ratio before the update."""
    lines = [f"| task | variant | runs | {unit} | error before update, PeVFA / VFA (median ratio) | PeVFA closer before "
             "| error after update, PeVFA / VFA | per run: seed, best return (median ratio before) |",
             "|---|---|---|---|---|---|---|---|"]  # fmt: skip
    for task, by_variant in runs.items():
        for variant, variant_runs in by_variant.items():
            series = diagnosed(variant_runs)
            if not series:
                continue
            kept = sorted((r for r in variant_runs if r.get("local_generalization")), key=lambda r: r.get("seed", 0))
            per_run = ", ".join(f"{r.get('seed', '?')}: {r.get('max_average_return', np.nan):.0f} "
                                f"({_median_ratio(r['local_generalization']):.2f})" for r in kept)  # fmt: skip
            errors = {key: np.concatenate([np.asarray(s[key], float) for s in series]) for key in
                      ("pevfa_before", "vfa_before", "pevfa_after", "vfa_after")}  # fmt: skip
            valid = np.all([np.isfinite(e) for e in errors.values()], axis=0)
            errors = {key: value[valid] for key, value in errors.items()}
            ratio = np.median(errors["pevfa_before"] / errors["vfa_before"])
            closer = np.mean(errors["pevfa_before"] < errors["vfa_before"])
            mean = {key: f"{np.mean(value):.3g}" for key, value in errors.items()}
            before = f"{mean['pevfa_before']} / {mean['vfa_before']} ({ratio:.2f})"
            after = f"{mean['pevfa_after']} / {mean['vfa_after']}"
            lines.append(f"| {task} | {variant} | {len(series)} | {int(valid.sum())} | {before} | {closer:.0%} | {after} "
                         f"| {per_run} |")  # fmt: skip
    return lines if len(lines) > 2 else []


def _median_ratio(series: dict[str, list[float]]) -> float:
    """The median over a run's iterations of PeVFA's error before the update over the conventional critic's."""
    ratio = np.asarray(series["pevfa_before"], float) / np.asarray(series["vfa_before"], float)
    return float(np.median(ratio[np.isfinite(ratio)])) if np.isfinite(ratio).any() else np.nan


def training_signals(runs: Runs) -> list[str]:
    """Per task and variant whose runs kept SB3's training log: each signal's mean over the last third of a run's
    iterations, mean over runs (— where the variant does not log it)."""
    lines = ["| task | variant | runs | " + " | ".join(SIGNALS.values()) + " |", "|---" * (len(SIGNALS) + 3) + "|"]
    for task, by_variant in runs.items():
        for variant in ordered_variants({task: by_variant}):
            logs = [r["training_log"] for r in by_variant[variant] if "training_log" in r]
            if not logs:
                continue
            cells = []
            for key in SIGNALS:
                tails = [np.asarray(log[key], float)[-(len(log[key]) // 3 or 1) :] for log in logs if log.get(key)]
                means = [float(np.nanmean(t)) for t in tails if np.isfinite(t).any()]
                cells.append(f"{np.mean(means):.3g}" if means else "—")
            lines.append(f"| {task} | {variant} | {len(logs)} | " + " | ".join(cells) + " |")
    return lines if len(lines) > 2 else []
