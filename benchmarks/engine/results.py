"""What a campaign's storage holds, for the report and the status: each grid point's completed runs (their trials'
user attributes), the progress of running trials, notes on failed or duplicated grid points, and the time the
campaigns take and have left."""

from typing import Any

import numpy as np
from optuna.trial import TrialState

from .definitions import CAMPAIGNS, Campaign
from .storage import (
    deaths,
    done,
    grid_states,
    is_stored,
    on_database,
    open_study,
    raised,
    retried_enough,
    running,
    storage_of,
    stored_names,
)

#: task -> variant -> the user attributes of its completed runs, one per seed
Runs = dict[str, dict[str, list[dict[str, Any]]]]


def collect(names: list[str], storage: str | None) -> tuple[Runs, dict, list[str], list[Campaign]]:
    """task -> variant -> the completed runs' user attributes (one per seed: a grid point's first complete trial),
    (task, variant) -> the progress of running trials, the notes on failed or duplicated grid points, and the
    campaigns. Variants are named ``protocol:variant`` where the campaigns mix protocols."""
    names = list(dict.fromkeys(names))  # a campaign named twice counts once
    runs: Runs = {}
    progress: dict[tuple[str, str], list[dict[str, float]]] = {}
    notes, resumed = [], []
    studies = [open_study(name, storage_of(name, storage)) for name in names]
    campaigns = [campaign for _, campaign in studies]
    for study, campaign in studies:
        by_number = {t.number: t for t in study.get_trials(deepcopy=False)}
        for (task, variant, seed), trials in grid_states(study, campaign).items():
            label = variant_label(campaign, variant, campaigns)
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
            elif trials and raised(trials[-1]):
                error = trials[-1].user_attrs["error"]
                notes.append(f"{task} {label} seed {seed}: trial {trials[-1].number} failed (its training raised {error})")
            elif trials and retried_enough(trials[-1], by_number):
                died = f"trial {trials[-1].number}'s worker died {deaths(trials[-1], by_number)} times"
                notes.append(f"{task} {label} seed {seed}: {died}: not retried again")
    if resumed:
        notes.insert(0, f"Went on from a checkpoint (task, variant, seed, at env step): {', '.join(resumed)}")
    order = list(dict.fromkeys(task for campaign in campaigns for task in campaign.tasks))
    return {task: runs[task] for task in order if task in runs}, progress, notes, campaigns


def variant_label(campaign: Campaign, variant: str, campaigns: list[Campaign]) -> str:
    """A variant's name among ``campaigns``: ``protocol:variant`` where they mix protocols."""
    return f"{campaign.protocol}:{variant}" if len({c.protocol for c in campaigns}) > 1 else variant


def run_times(runs: Runs, progress: dict, campaigns: list[Campaign]) -> dict[tuple[str, str], np.ndarray]:
    """(CPU, wall-clock) seconds of a whole run, training and evaluation, per task and variant label: the completed
    runs' mean, else extrapolated from running trials' progress (training only)."""
    times: dict[tuple[str, str], np.ndarray] = {}
    for task, by_variant in runs.items():
        for variant, variant_runs in by_variant.items():
            cpu = np.mean([r["cpu_seconds"] + r["eval_cpu_seconds"] for r in variant_runs])
            wall = np.mean([r["wall_seconds"] + r["eval_wall_seconds"] for r in variant_runs])
            times[task, variant] = np.array([cpu, wall])
    for campaign in campaigns:
        for task, variant, _ in campaign.grid:
            key = (task, variant_label(campaign, variant, campaigns))
            if key not in times and progress.get(key):
                measured = np.mean([(p["cpu_s"], p["wall_s"]) for p in progress[key]], 0)
                times[key] = measured / np.mean([p["steps"] for p in progress[key]]) * campaign.timesteps
    return times


def expected_duration(runs: Runs, progress: dict, campaigns: list[Campaign], workers: int) -> str:
    """The campaigns' CPU time and the wall-clock time left (a running trial's less its training so far). A run's
    time per task and variant: :func:`run_times`, else :func:`scaled_time`; grid points with none are counted apart."""
    times = run_times(runs, progress, campaigns)
    points = [((task, variant_label(c, variant, campaigns)), seed) for c in campaigns for task, variant, seed in c.grid]
    total = remaining = 0.0
    unknown = 0
    for key, seed in points:
        time = time_of(times, key)
        elapsed = max([p["wall_s"] for p in progress.get(key, []) if p.get("seed") == seed], default=0.0)
        done = any(r["seed"] == seed for r in runs.get(key[0], {}).get(key[1], []))
        if time is None:
            unknown += not done
            continue
        total += time[0]
        remaining += 0.0 if done else max(time[1] - elapsed, 0.0)  # a running trial: what it has left
    if not remaining and not unknown:
        return f"Duration: {total / 3600:.1f} CPU-hours of training and evaluation in all, nothing left to run."
    if not total:
        return (f"Expected duration: not known yet: no run of these variants, nor of their protocol's other variants on "
                f"these tasks, to estimate the {unknown} runs left from (a campaign of the same protocol named beside "
                "this one lends its runs' times).")  # fmt: skip
    text = (f"Expected duration: about {total / 3600:.1f} CPU-hours in all, {remaining / 3600 / workers:.1f} wall-clock hours "
            f"left on {workers} workers (from the runs' mean times per task and variant, else running trials' "
            "progress, else other variants' times scaled by their ratio, else, for a variant with no run yet, the "
            "mean of its protocol's other variants on the task).")  # fmt: skip
    if unknown:
        text += f" Not counted: {unknown} runs of variants with no run yet."
    return text


def time_of(times: dict[tuple[str, str], np.ndarray], key: tuple[str, str]) -> np.ndarray | None:
    """A run's (CPU, wall-clock) seconds: measured (:func:`run_times`), else :func:`scaled_time`."""
    return times[key] if key in times else scaled_time(times, key)


def scaled_time(times: dict[tuple[str, str], np.ndarray], key: tuple[str, str]) -> np.ndarray | None:
    """A variant's time on a task: another variant's time there times their mean ratio on the tasks where both ran,
    else the variant's mean over the tasks where it ran, else (a variant with no run yet) the mean time of its
    protocol's other variants on the task; None where none of these has a time."""
    task, variant = key
    own = [k for k in times if k[1] == variant]
    estimates = [
        times[task, other] * np.mean([times[t, variant] / times[t, other] for t, _ in own if (t, other) in times], 0)
        for t_, other in times
        if t_ == task and any((t, other) in times for t, _ in own)
    ]
    if estimates:
        return np.mean(estimates, 0)
    if own:
        return np.mean([times[k] for k in own], 0)
    protocol = variant.rpartition(":")[0]  # "" where the campaigns share one protocol (plain variant names)
    peers = [times[k] for k in times if k[0] == task and k[1].rpartition(":")[0] == protocol]
    return np.mean(peers, 0) if peers else None


def status(names: list[str], storage: str | None, workers: int) -> None:
    """Each grid point's trials, then the campaigns' expected duration (the report's estimate)."""
    for name in names:
        status_of(name, storage)
    runs, progress, _, campaigns = collect(names, storage)
    print(expected_duration(runs, progress, campaigns, workers))


def overview(storage: str | None) -> None:
    """One line per campaign, the repository's and those the storage holds: its grid and how much of it is done."""
    for name in dict.fromkeys([*CAMPAIGNS, *stored_names(storage)]):
        if is_stored(name, storage):
            study, campaign = open_study(name, storage_of(name, storage))
            complete, active = done(study, campaign), running(study, campaign)
        else:  # not started: no journal file is created to say so
            campaign, complete, active = CAMPAIGNS[name], 0, 0
        grid = f"{len(campaign.tasks)} tasks x {len(campaign.variants)} variants x {len(campaign.seeds)} seeds"
        counts = f"{complete}/{len(campaign.grid)} complete" + (f", {active} running" if active else "")
        print(f"{name:38s} {campaign.protocol:7s} {grid}, {campaign.timesteps:,} steps: {counts}")


def status_of(name: str, storage: str | None) -> None:
    """A campaign's grid points complete, its trials by state, and each grid point's trials."""
    study, campaign = open_study(name, storage_of(name, storage))
    counts: dict[str, int] = {}
    for trial in study.get_trials(deepcopy=False):
        counts[trial.state.name] = counts.get(trial.state.name, 0) + 1
    print(f"{name}: {done(study, campaign)}/{len(campaign.grid)} grid points complete; trials by state {counts}")
    database = on_database(study)
    for (task, variant, seed), trials in grid_states(study, campaign).items():
        states = " ".join(f"#{t.number}:{t.state.name}{trial_outcome(t, database)}" for t in trials)
        print(f"  {task:28s} {variant:26s} seed {seed}: {states or '-'}")


def trial_outcome(trial: Any, database: bool = False) -> str:
    """What the status adds to a trial's state: its max average return, a running one's progress (env steps and
    training CPU time at its last evaluation), or why a failed one stopped: interrupted (the worker was stopped or
    died, and the grid point is tried again; the checkpoint it saved and its last evaluation, if any), its training
    raised (with the exception), or, without a reason kept, a dead worker that Optuna's heartbeat failed (a
    ``database``) or an unknown one."""
    if trial.value is not None:
        return f" (max average return {trial.value:.0f})"
    progress = trial.user_attrs.get("progress") or {}
    at = (f"last evaluation at {progress['steps']:,} env steps, {progress['cpu_s'] / 60:.1f} CPU-min"
          if {"steps", "cpu_s"} <= progress.keys() else "")  # fmt: skip
    if trial.state == TrialState.RUNNING and at:
        return f" ({at})"
    if trial.state == TrialState.PRUNED:  # a worker drew a grid point another trial held
        held = trial.user_attrs.get("duplicate_of")
        return " (a duplicate)" if held is None else f" (a duplicate of #{held})"
    if trial.state != TrialState.FAIL:
        return ""
    checkpoint = trial.user_attrs.get("checkpoint")
    kept = [f"checkpoint at {checkpoint['steps']:,} env steps on {checkpoint['host']}"] if checkpoint else []
    where = "".join(f"; {part}" for part in [*kept, at] if part)
    if trial.user_attrs.get("interrupted"):
        return f" (interrupted: {trial.user_attrs['interrupted']}{where})"
    if "error" in trial.user_attrs:
        return f" (raised {trial.user_attrs['error']})"
    return f" (interrupted: worker gone{where})" if database else " (failed: no reason kept, tried again)"
