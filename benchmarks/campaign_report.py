"""The report of learning campaigns (``campaign.py``), built from their storage alone (no rerun).

Table 1's layout (max average return, mean +- half a std over seeds, per task and variant, with each variant's
ratio to the baseline), beside the paper's published values where the protocol is the paper's or the authors'; the
IQM of baseline-normalized scores over tasks with stratified bootstrap 95 % CIs, the probability of improvement over the
baseline and a performance profile; speed (env steps per CPU-second, wall-clock beside) and the best-so-far return
at the baseline's CPU time; each trial's time and the campaign's expected duration; learning curves per env step
and per CPU-second (one PNG, a column per task).

    python benchmarks/campaign_report.py --campaign table1 table1-default-schedule --out docs/results/paper-protocol
"""

import argparse
import pathlib
import warnings
from typing import Any

import aggregate
import numpy as np
import optuna
from campaign import LOCAL_GENERALIZATION, Campaign, deaths, grid_states, open_study, retried_enough, storage_of
from optuna.trial import TrialState

from sb3_pevfa.protocols import AUTHORS_DEVIATIONS, PAPER_DEVIATIONS

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
TARGET = {"variant": "opr-e2e", "tasks": 5, "iqm": 1.15, "low": 1.0}
#: Protocols whose reports stand beside the paper's Table 1 and its target: what each one's deviations are from
PUBLISHED = {"paper": ("the paper", PAPER_DEVIATIONS), "authors": ("the authors' code", AUTHORS_DEVIATIONS)}
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


Runs = dict[str, dict[str, list[dict[str, Any]]]]


def collect(names: list[str], storage: str | None) -> tuple[Runs, dict, list[str], list[Campaign]]:
    """task -> variant -> the completed runs' user attributes (one per seed: a grid point's first complete trial),
    (task, variant) -> the progress of running trials, the notes on failed or duplicated grid points, and the
    campaigns. Variants are named ``protocol:variant`` where the campaigns mix protocols."""
    names = list(dict.fromkeys(names))  # a campaign named twice counts once
    runs: Runs = {}
    progress: dict[tuple[str, str], list[dict[str, float]]] = {}
    notes, campaigns, resumed = [], [], []
    studies = [open_study(name, storage_of(name, storage)) for name in names]
    mixed = len({campaign.protocol for _, campaign in studies}) > 1
    for study, campaign in studies:
        campaigns.append(campaign)
        by_number = {t.number: t for t in study.get_trials(deepcopy=False)}
        for (task, variant, seed), trials in grid_states(study, campaign).items():
            label = f"{campaign.protocol}:{variant}" if mixed else variant
            complete = [t for t in trials if t.state == TrialState.COMPLETE]
            running = [
                {**t.user_attrs["progress"], "seed": seed}
                for t in trials
                if t.state == TrialState.RUNNING and "progress" in t.user_attrs
            ]
            progress.setdefault((task, label), []).extend(running)
            if complete:
                runs.setdefault(task, {}).setdefault(label, []).append({**complete[0].user_attrs, "seed": seed})
                if complete[0].user_attrs.get("resumed_from"):
                    resumed.append(f"{task} {label} {seed} ({complete[0].user_attrs['resumed_from']:,})")
                if len(complete) > 1:
                    notes.append(f"{task} {label} seed {seed} completed {len(complete)} times: the first one counts")
            elif trials and trials[-1].state == TrialState.FAIL and not trials[-1].user_attrs.get("interrupted"):
                notes.append(f"{task} {label} seed {seed}: trial {trials[-1].number} failed (its training raised)")
            elif trials and retried_enough(trials[-1], by_number):
                died = f"trial {trials[-1].number}'s worker died {deaths(trials[-1], by_number)} times"
                notes.append(f"{task} {label} seed {seed}: {died}: not retried again")
    if resumed:
        notes.insert(0, f"Went on from a checkpoint (task, variant, seed, at env step): {', '.join(resumed)}")
    order = list(dict.fromkeys(task for campaign in campaigns for task in campaign.tasks))
    return {task: runs[task] for task in order if task in runs}, progress, notes, campaigns


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


def _variants(runs: Runs) -> list[str]:
    """The variants of the runs, in Table 1's column order."""
    present = {v for by_variant in runs.values() for v in by_variant}
    return sorted(present, key=lambda v: (ORDER.index(v.split(":")[-1]) if v.split(":")[-1] in ORDER else len(ORDER), v))


def _compared(runs: Runs) -> list[str]:
    """The variants that the aggregates, the speed and the curves compare: all but the diagnostic's,
    whose runs train an extra critic (their time) and draw other random numbers (their returns: in the table only)."""
    return [v for v in _variants(runs) if v.split(":")[-1] not in LOCAL_GENERALIZATION]


def table(runs: Runs, baseline: str, paper: bool) -> list[str]:
    variants = _variants(runs)
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
    for variant in _compared(runs):
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


def target(runs: Runs, baseline: str, planned: dict[str, int]) -> list[str]:
    """The target read from the runs of its variant (``TARGET["variant"]``): the tasks above the baseline's mean (by
    more than ``TIE``), the IQM with its CI (as in ``aggregates``), and met, or missed by how much; provisional while
    the variant or the baseline has fewer runs than ``planned`` (variant -> runs in its campaigns' grids; the
    report's, where every campaign is of the paper's protocol, so that no variant name carries a protocol)."""
    variant = TARGET["variant"]
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
    short = [f"{TARGET['tasks'] - above} task(s)"] if above < TARGET["tasks"] else []
    short += [f"{TARGET['iqm'] - value:.3f} of IQM"] if value < TARGET["iqm"] else []
    short += [f"{TARGET['low'] - low:.3f} of the lower bound"] if low <= TARGET["low"] else []
    made = {v: sum(len(by_variant.get(v, [])) for by_variant in runs.values()) for v in (variant, baseline)}
    missing = {v: planned.get(v, 0) - made[v] for v in made if made[v] < planned.get(v, 0)}
    apart = "; ".join(f"{word} on {', '.join(named)}" for word, named in (("tied", tied), ("below", below)) if named)
    return [
        f"- {variant}: above {baseline} on {above} of {len(tasks)} tasks"
        + (f" ({apart})" if apart else "")
        + f", IQM {value:.2f} [{low:.2f}, {high:.2f}]: "
        + ("met" if not short else "missed by " + ", ".join(short))
        + (f"; provisional, runs to come: {', '.join(f'{n} of {v}' for v, n in missing.items())}" if missing else "")
    ]


def same_machine(run: dict[str, Any], base_runs: list[dict[str, Any]]) -> list[dict[str, Any]]:
    """The baseline runs made on the machine (the boot) that made ``run``, or all of them where none was."""
    boot = run.get("worker", {}).get("boot_id")
    return [b for b in base_runs if boot and b.get("worker", {}).get("boot_id") == boot] or base_runs


def at_baseline_cpu(run: dict[str, Any], base_runs: list[dict[str, Any]]) -> float:
    """The run's best evaluation within the mean training CPU time of the baseline's runs on its machine."""
    return best_so_far_at(run, float(np.mean([b["cpu_seconds"] for b in same_machine(run, base_runs)])))


def speed(runs: Runs, baseline: str) -> list[str]:
    """Per task: the baseline's steps per CPU-second (wall-clock) and CPU minutes per run; per other variant, its
    speed per CPU-second (wall-clock) and best-so-far return within the baseline's mean CPU time, as ratios to the
    baseline's runs on the same machine where there are any (a campaign spans machines), and its CPU minutes."""
    variants = [v for v in _compared(runs) if v != baseline]
    lines = [f"| task | {baseline} | " + " | ".join(variants) + " |",
             "|---" * (len(variants) + 2) + "|"]  # fmt: skip

    def mean(values: list[float]) -> float:
        return float(np.mean(values)) if values else np.nan

    def ratio(run: dict[str, Any], base_runs: list[dict[str, Any]], key: str) -> float:
        return run[key] / mean([b[key] for b in same_machine(run, base_runs)])

    for task, by_variant in runs.items():
        base_runs = by_variant.get(baseline, [])
        base_cpu = mean([r["cpu_seconds"] for r in base_runs])
        base_best = mean([at_baseline_cpu(r, base_runs) for r in base_runs])
        base_speed = mean([r["steps_per_cpu_second"] for r in base_runs])
        base_wall = mean([r["steps_per_wall_second"] for r in base_runs])
        cells = [f"{base_speed:.0f} ({base_wall:.0f}), {base_cpu / 60:.0f}" if base_runs else "—"]
        for variant in variants:
            variant_runs = by_variant.get(variant, [])
            if not variant_runs or not base_runs:
                cells.append("—")
                continue
            cpu_speed = mean([ratio(r, base_runs, "steps_per_cpu_second") for r in variant_runs])
            wall_speed = mean([ratio(r, base_runs, "steps_per_wall_second") for r in variant_runs])
            best = mean([at_baseline_cpu(r, base_runs) for r in variant_runs])
            best_ratio = f"{best / base_best:.2f}x" if np.isfinite(best) and base_best > 0 else "—"
            minutes = mean([r["cpu_seconds"] for r in variant_runs]) / 60
            cells.append(f"{cpu_speed:.2f}x ({wall_speed:.2f}x), {best_ratio}, {minutes:.0f}")
        lines.append(f"| {task} | " + " | ".join(cells) + " |")
    return lines


def _diagnosed(variant_runs: list[dict[str, Any]]) -> list[dict[str, list[float]]]:
    """The diagnostic's series of the runs that kept it from start to end: a run that went on from a checkpoint
    started a new conventional critic there (the callback is not checkpointed), so it is left out."""
    return [r["local_generalization"] for r in variant_runs if "local_generalization" in r and not r.get("resumed_from")]


def local_generalization(runs: Runs) -> list[str]:
    """Per task and variant with the diagnostic: the PeVFA's and the conventional critic's errors against the
    Monte-Carlo returns of each new policy before and after the iteration's critic update (paper Fig. 3b / 8), over
    the runs of ``_diagnosed``."""
    lines = ["| task | variant | runs | iterations | error before update, PeVFA / VFA (median ratio) | PeVFA closer before "
             "| error after update, PeVFA / VFA |", "|---|---|---|---|---|---|---|"]  # fmt: skip
    for task, by_variant in runs.items():
        for variant, variant_runs in by_variant.items():
            series = _diagnosed(variant_runs)
            if not series:
                continue
            errors = {key: np.concatenate([np.asarray(s[key], float) for s in series]) for key in
                      ("pevfa_before", "vfa_before", "pevfa_after", "vfa_after")}  # fmt: skip
            valid = np.all([np.isfinite(e) for e in errors.values()], axis=0)
            errors = {key: value[valid] for key, value in errors.items()}
            ratio = np.median(errors["pevfa_before"] / errors["vfa_before"])
            closer = np.mean(errors["pevfa_before"] < errors["vfa_before"])
            mean = {key: f"{np.mean(value):.3g}" for key, value in errors.items()}
            before = f"{mean['pevfa_before']} / {mean['vfa_before']} ({ratio:.2f})"
            after = f"{mean['pevfa_after']} / {mean['vfa_after']}"
            lines.append(f"| {task} | {variant} | {len(series)} | {int(valid.sum())} | {before} | {closer:.0%} | {after} |")
    return lines if len(lines) > 2 else []


def local_generalization_curves(series: list[dict[str, list[float]]], window: int = 25) -> dict[str, np.ndarray]:
    """A task's diagnostic runs, per iteration (runs aligned by iteration): the env steps and, before and after the
    critic update, the PeVFA's error over the conventional critic's, as a geometric mean over runs smoothed by a
    centered moving geometric mean over ``window`` iterations (non-finite errors left out)."""
    n = min(len(s["timesteps"]) for s in series)
    curves = {"steps": np.asarray(series[0]["timesteps"][:n], float)}
    with np.errstate(divide="ignore", invalid="ignore"), warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)  # the mean of an all-NaN slice is NaN
        for when in ("before", "after"):
            logs = np.log(np.array([np.asarray(s[f"pevfa_{when}"][:n], float) / np.asarray(s[f"vfa_{when}"][:n], float)
                                    for s in series]))  # fmt: skip
            logs[~np.isfinite(logs)] = np.nan
            per_iteration = np.nanmean(logs, axis=0)
            first = [i - window // 2 for i in range(n)]  # each window: ``window`` iterations around i, cut at the ends
            curves[when] = np.exp([np.nanmean(per_iteration[max(0, f) : f + window]) for f in first])
    return curves


def plot_local_generalization(runs: Runs, png: pathlib.Path) -> None:
    """One panel per task with diagnostic runs: PeVFA's error / the conventional critic's over training."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    panels = [(task, variant, _diagnosed(variant_runs))
              for task, by_variant in runs.items() for variant, variant_runs in by_variant.items()]  # fmt: skip
    panels = [panel for panel in panels if panel[2]]
    figure, axes = plt.subplots(1, len(panels), figsize=(4.5 * len(panels), 3.4), squeeze=False)
    for ax, (task, variant, series) in zip(axes[0], panels):
        curves = local_generalization_curves(series)
        ax.plot(curves["steps"] / 1e6, curves["before"], label="before the critic update")
        ax.plot(curves["steps"] / 1e6, curves["after"], "--", label="after")
        ax.axhline(1.0, color="grey", linewidth=0.8)
        ax.set(yscale="log", xlabel="env steps (M)", title=f"{task}, {variant} ({len(series)} runs)")
        ax.title.set_fontsize(9)
    axes[0][0].set_ylabel("PeVFA's error / conventional critic's")
    axes[0][0].legend(fontsize=7)
    figure.tight_layout()
    figure.savefig(png, dpi=80)
    plt.close(figure)


def training_signals(runs: Runs) -> list[str]:
    """Per task and variant whose runs kept SB3's training log: each signal's mean over the last third of a run's
    iterations, mean over runs (— where the variant does not log it)."""
    lines = ["| task | variant | runs | " + " | ".join(SIGNALS.values()) + " |", "|---" * (len(SIGNALS) + 3) + "|"]
    for task, by_variant in runs.items():
        for variant in _variants({task: by_variant}):
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


def expected_duration(runs: Runs, progress: dict, campaigns: list[Campaign], workers: int) -> str:
    """The campaigns' CPU time and the wall-clock time left (a running trial's less its training so far). A run's
    time per task and variant: the completed runs' mean, else extrapolated from running trials' progress (training
    only), else scaled from another variant's time on the task by the two variants' ratio where both ran, else the
    variant's mean; grid points with none are counted apart."""
    times: dict[tuple[str, str], np.ndarray] = {}  # (CPU, wall-clock) seconds per run
    for task, by_variant in runs.items():
        for variant, variant_runs in by_variant.items():
            cpu = np.mean([r["cpu_seconds"] + r["eval_cpu_seconds"] for r in variant_runs])
            wall = np.mean([r["wall_seconds"] + r["eval_wall_seconds"] for r in variant_runs])
            times[task, variant] = np.array([cpu, wall])
    mixed = len({c.protocol for c in campaigns}) > 1
    points = [
        (c, (task, f"{c.protocol}:{variant}" if mixed else variant), seed) for c in campaigns for task, variant, seed in c.grid
    ]
    for campaign, key, _ in points:
        if key not in times and progress.get(key):
            measured = np.mean([(p["cpu_s"], p["wall_s"]) for p in progress[key]], 0)
            times[key] = measured / np.mean([p["steps"] for p in progress[key]]) * campaign.timesteps
    total = remaining = 0.0
    unknown = 0
    for _, key, seed in points:
        time = times[key] if key in times else scaled_time(times, key)
        elapsed = max([p["wall_s"] for p in progress.get(key, []) if p.get("seed") == seed], default=0.0)
        done = any(r["seed"] == seed for r in runs.get(key[0], {}).get(key[1], []))
        if time is None:
            unknown += not done
            continue
        total += time[0]
        remaining += 0.0 if done else max(time[1] - elapsed, 0.0)  # a running trial: what it has left
    if not remaining and not unknown:
        return f"Duration: {total / 3600:.1f} CPU-hours of training and evaluation in all, nothing left to run."
    text = (f"Expected duration: about {total / 3600:.1f} CPU-hours in all, {remaining / 3600 / workers:.1f} wall-clock hours "
            f"left on {workers} workers (from the runs' mean times per task and variant, else running trials' "
            "progress, else other variants' times scaled by their ratio).")  # fmt: skip
    if unknown:
        text += f" Not counted: {unknown} runs of variants with no run yet."
    return text


def scaled_time(times: dict[tuple[str, str], np.ndarray], key: tuple[str, str]) -> np.ndarray | None:
    """A variant's time on a task: another variant's time there times their mean ratio on the tasks where both ran,
    else the variant's mean over the tasks where it ran; None where the variant has no time yet."""
    task, variant = key
    own = [k for k in times if k[1] == variant]
    estimates = [
        times[task, other] * np.mean([times[t, variant] / times[t, other] for t, _ in own if (t, other) in times], 0)
        for t_, other in times
        if t_ == task and any((t, other) in times for t, _ in own)
    ]
    if estimates:
        return np.mean(estimates, 0)
    return np.mean([times[k] for k in own], 0) if own else None


def plot(runs, png: pathlib.Path, normalized: dict[str, aggregate.TaskScores]) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    tasks = list(runs)
    figure, axes = plt.subplots(2, len(tasks) + 1, figsize=(3.4 * (len(tasks) + 1), 6.0), squeeze=False)
    colors = {}
    compared = _compared(runs)  # the diagnostic's runs are slower by their extra critic
    for column, task in enumerate(tasks):
        for variant, variant_runs in runs[task].items():
            if variant not in compared:
                continue
            color = colors.setdefault(variant, f"C{len(colors)}")
            n = min(len(r["curve"]["mean"]) for r in variant_runs)
            means = np.array([r["curve"]["mean"][:n] for r in variant_runs])
            steps = np.array(variant_runs[0]["curve"]["steps"][:n])
            cpu = np.mean([r["curve"]["cpu_s"][:n] for r in variant_runs], axis=0) / 60
            for row, x in enumerate((steps / 1e6, cpu)):
                ax = axes[row][column]
                ax.plot(x, means.mean(0), color=color, label=f"{variant} ({len(variant_runs)})")
                ax.fill_between(x, means.mean(0) - means.std(0) / 2, means.mean(0) + means.std(0) / 2, color=color, alpha=0.2)
        axes[0][column].set_title(task, fontsize=9)
        axes[0][column].set_xlabel("env steps (M)")
        axes[1][column].set_xlabel("training CPU minutes")
        axes[0][column].legend(fontsize=7)
    axes[0][0].set_ylabel("evaluation return (mean ± half std)")
    axes[1][0].set_ylabel("evaluation return (mean ± half std)")
    taus = np.linspace(0, 2.5, 101)
    ax = axes[0][-1]
    for variant, scores in normalized.items():
        low, high = aggregate.profile_band(scores, taus)
        ax.plot(taus, aggregate.performance_profile(scores, taus), color=colors.get(variant), label=variant)
        ax.fill_between(taus, low, high, color=colors.get(variant), alpha=0.2)
    ax.set_title("performance profile", fontsize=9)
    ax.set_xlabel("max average return / baseline's mean")
    ax.set_ylabel("fraction of runs above")
    ax.legend(fontsize=7)
    axes[1][-1].axis("off")
    figure.tight_layout()
    png.parent.mkdir(parents=True, exist_ok=True)
    figure.savefig(png, dpi=80)
    plt.close(figure)


def report(names: list[str], storage: str | None, baseline: str, workers: int, png: pathlib.Path | None) -> str:
    runs, progress, notes, campaigns = collect(names, storage)
    protocols = {c.protocol for c in campaigns}
    paper = len(protocols) == 1 and protocols <= set(PUBLISHED)
    complete = sum(len(rs) for bv in runs.values() for rs in bv.values())
    total = sum(len(c.grid) for c in campaigns)
    lines = [f"Campaigns {', '.join(names)}: {complete} of {total} runs complete.", ""]
    if not runs:
        return "\n".join(lines)
    commits = sorted({r["commit"] for bv in runs.values() for rs in bv.values() for r in rs})
    machines = sorted({r["machine"] for bv in runs.values() for rs in bv.values() for r in rs})
    made = [r for bv in runs.values() for rs in bv.values() for r in rs]
    versions = {name: "/".join(sorted({str(r["versions"].get(name, "?")) for r in made})) for name in made[0]["versions"]}
    flipped = [t for t, bv in runs.items() if bv.get(baseline) and t not in comparable(runs, baseline, baseline)]
    if flipped:
        notes.append(f"Left out of the aggregates and the target: {', '.join(flipped)}, where {baseline}'s mean is not "
                     "positive (a ratio to it would reverse the order of the scores)")  # fmt: skip
    steps = "/".join(f"{s:,}" for s in sorted({c.timesteps for c in campaigns}))
    beside = " beside the paper's Table 1 (2M steps, 4M on Ant, 10 seeds)" if paper else ""
    aggregate_lines, normalized = aggregates(runs, baseline)
    zoo = [c for c in campaigns if c.protocol == "zoo"]  # an rl-zoo3 training times its evaluations with itself
    apart = "apart" if not zoo else "included" if len(zoo) == len(campaigns) else "apart, included in protocol zoo's runs"
    sections = [
        [f"Max average return (mean ± half std over seeds, runs in brackets), {steps} env steps, and each variant's "
         f"ratio to {baseline}'s mean{beside}:"],
        table(runs, baseline, paper),
        [f"Over tasks: each run's max average return / {baseline}'s mean on its task (95 % stratified-bootstrap CIs "
         f"over the seeds of both); at {baseline}'s CPU time: its best return within {baseline}'s mean training CPU "
         "time (same task and machine):"],
        aggregate_lines,
    ]  # fmt: skip
    if paper:
        planned: dict[str, int] = {}
        for c in campaigns:
            for variant in c.variants:
                planned[variant] = planned.get(variant, 0) + len(c.tasks) * len(c.seeds)
        sections += [[f"Against the target for {TARGET['variant']} (above {baseline}'s mean on at least {TARGET['tasks']} "
                      f"of Table 1's 6 tasks, IQM at least {TARGET['iqm']} with the CI's lower bound above {TARGET['low']}):"],
                     target(runs, baseline, planned)]  # fmt: skip
        ratios = {v: np.mean([PAPER_TABLE1[t][v][0] / PAPER_TABLE1[t]["ppo"][0] for t in PAPER_TABLE1]) for v in ORDER[1:5]}
        sections.append(
            ["The paper's ratios to its PPO, mean over its six tasks: " + ", ".join(f"{v} {r:.2f}" for v, r in ratios.items())]
        )
    sections += [
        [f"Speed: {baseline}'s env steps per CPU-second (wall-clock beside; evaluations {apart}), CPU minutes per run; "
         f"each variant's speed (wall) and best return within {baseline}'s CPU time as ratios, its CPU minutes:"],
        speed(runs, baseline),
        [expected_duration(runs, progress, campaigns, workers)],
    ]  # fmt: skip
    diagnostic = local_generalization(runs)
    if diagnostic:
        sections += [["Local generalization (the paper's Fig. 3b / 8): mean squared error on each new policy's "
                      "Monte-Carlo returns, PeVFA against a conventional critic trained beside it (over training: "
                      "local_generalization.png); its runs are in the first table only (the extra critic costs time):"],
                     diagnostic]  # fmt: skip
    signals = training_signals(runs)
    if signals:
        sections += [["Training signals from SB3's logs (mean over each run's last third of iterations, then over "
                      "runs): the on-policy critic's explained variance, the PeVFA's loss on historical samples, "
                      "the norm of the value's gradient in chi (does the critic read chi?), chi's norm and its "
                      "share of saturated units:"], signals]  # fmt: skip
    if paper:
        source, deviations = PUBLISHED[protocols.pop()]
        sections += [[f"Deviations from {source}:"], [f"- {d}" for d in deviations]]
    libraries = ", ".join(f"{name} {versions[name]}" for name in ("torch", "stable_baselines3", "gymnasium", "mujoco"))
    sections.append([f"Runs made at commits {', '.join(commits)} on {', '.join(machines)}; {libraries}."])
    sections.append([f"- {note}" for note in notes])
    lines += [line for section in sections if section for line in (*section, "")]
    if png is not None:
        plot(runs, png, normalized)
        if diagnostic:
            plot_local_generalization(runs, png.with_name("local_generalization.png"))
    return "\n".join(lines).rstrip() + "\n"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--campaign", nargs="+", required=True)
    parser.add_argument("--storage", default=None, help="database URL or journal file (default: benchmarks/campaigns/)")
    parser.add_argument("--baseline", default="ppo", help="the variant every ratio is to")
    parser.add_argument("--workers", type=int, default=2, help="cores the expected duration is for")
    parser.add_argument("--out", type=pathlib.Path, default=None, help="write report.md and curves.png in this folder")
    args = parser.parse_args()
    optuna.logging.set_verbosity(optuna.logging.WARNING)
    png = args.out / "curves.png" if args.out else None
    text = report(args.campaign, args.storage, args.baseline, args.workers, png)
    if args.out:
        (args.out / "report.md").write_text(text)
    print(text)


if __name__ == "__main__":
    main()
