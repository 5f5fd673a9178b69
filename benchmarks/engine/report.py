"""The report of learning campaigns, from their storage alone (no rerun): the tables (``tables``) in one markdown
text, the figures (``figures``) beside it."""

import pathlib
from typing import Any

import numpy as np

from sb3_pevfa.protocols import AUTHORS_DEVIATIONS, PAPER_DEVIATIONS

from .definitions import OFF_POLICY, Campaign, is_diagnostic
from .figures import plot, plot_beside, plot_local_generalization
from .results import Runs, collect, expected_duration
from .tables import (
    ORDER,
    PAPER_TABLE1,
    TARGETS,
    aggregates,
    baseline_beside,
    beside,
    compact,
    comparable,
    compared_variants,
    local_generalization,
    speed,
    table,
    target,
    target_wording,
    training_signals,
)

#: Protocols whose reports stand beside the paper's Table 1 and its target: what each one's deviations are from
PUBLISHED = {"paper": ("the paper", PAPER_DEVIATIONS), "authors": ("the authors' code", AUTHORS_DEVIATIONS)}
#: What the local-generalization diagnostic scores in the off-policy protocols (:class:`QLocalGeneralizationCallback`)
OFF_POLICY_SCORED = ("the discounted returns (SAC's with its entropy bonus) of the transitions each new snapshot's "
                     "actor collected until the next snapshot (a window), by Q(s, a) before and after the critics "
                     "learn from them")  # fmt: skip
#: How the report names a protocol where its name alone would read oddly
PROTOCOL_NAMES = {"authors": "authors' protocol"}


#: What ``collect`` reads from the storage: runs, progress, notes, campaigns
Collected = tuple[Runs, dict, list[str], list[Campaign]]


def read(names: list[str], storage: str | None, cache: dict[tuple, Collected] | None = None) -> Collected:
    """``collect(names, storage)``, once per ``cache`` (a report and its summary then read the same runs while workers
    write the storage)."""
    if cache is None:
        return collect(names, storage)
    key = (tuple(names), storage)
    if key not in cache:
        cache[key] = collect(names, storage)
    return cache[key]


def left_out(runs: Runs, baseline: str) -> list[str]:
    """The note on the tasks that the aggregates and the target leave out (the baseline's mean not positive)."""
    flipped = [t for t, bv in runs.items() if bv.get(baseline) and t not in comparable(runs, baseline, baseline)]
    if not flipped:
        return []
    return [f"Left out of the aggregates and the target: {', '.join(flipped)}, where {baseline}'s mean is not positive "
            "(a ratio to it would reverse the order of the scores)"]  # fmt: skip


def protocol_label(campaigns: list[Campaign]) -> str:
    """The campaigns' protocol(s) as the report names them."""
    return "/".join(sorted({PROTOCOL_NAMES.get(c.protocol, f"{c.protocol} protocol") for c in campaigns}))


def counted(runs: Runs, campaigns: list[Campaign], diagnostic: bool = False) -> tuple[int, int]:
    """The runs complete and the runs of the campaigns' grids, of the diagnostic variants or of the others."""
    complete = sum(len(rs) for bv in runs.values() for v, rs in bv.items() if is_diagnostic(v) == diagnostic)
    return complete, sum(len(c.tasks) * len(c.seeds) for c in campaigns for v in c.variants if is_diagnostic(v) == diagnostic)


def runs_complete(runs: Runs, campaigns: list[Campaign]) -> tuple[str, bool]:
    """The runs complete as the report says it ("64 of 90 runs complete", the diagnostic's apart), and whether all are."""
    complete, total = counted(runs, campaigns)
    text = f"{complete} of {total} runs complete"
    diagnosed, planned = counted(runs, campaigns, diagnostic=True)
    if planned:
        text += f" (and {diagnosed} of {planned} runs of the local-generalization diagnostic)"
    return text, complete + diagnosed == total + planned


def target_of(runs: Runs, campaigns: list[Campaign], baseline: str) -> tuple[dict[str, Any] | None, list[str]]:
    """The campaigns' target (where they are of one protocol that has one) and its reading from the runs."""
    protocols = {c.protocol for c in campaigns}
    spec = TARGETS.get(next(iter(protocols))) if len(protocols) == 1 else None
    if spec is None:
        return None, []
    planned: dict[str, int] = {}
    for c in campaigns:
        for variant in c.variants:
            planned[variant] = planned.get(variant, 0) + len(c.tasks) * len(c.seeds)
    return spec, target(runs, baseline, planned, spec)


def summary(
    names: list[str],
    storage: str | None,
    baseline: str,
    beside_names: list[str] | None = None,
    cache: dict[tuple, Collected] | None = None,
) -> str:
    """A results page's share of the report: the runs complete, per task the target's variant (else the first
    compared) against the baseline (``tables.compact``; beside it, per env step, ``beside_names``' protocol), the
    aggregates over tasks and the target's reading; ``cache``: as :func:`read`'s."""
    runs, _, _, campaigns = read(names, storage, cache)
    text, all_complete = runs_complete(runs, campaigns)
    steps = "/".join(f"{s:,}" for s in sorted({c.timesteps for c in campaigns}))
    head = f"{text}, {steps} env steps per run" + ("." if all_complete else " (provisional).")
    spec, lines_of_target = target_of(runs, campaigns, baseline)
    variants = [v for v in compared_variants(runs) if v != baseline]
    if not runs or not variants:
        return head + "\n"
    lines = [f"{head} Best evaluation (mean ± half std over seeds, runs in brackets) and the ratios to {baseline}'s:", ""]
    variant = spec["variant"] if spec is not None and spec["variant"] in variants else variants[0]
    other, label, apart = None, "", []
    if beside_names:
        other, _, _, others = read(beside_names, storage, cache)
        label = protocol_label(others)
        done, planned = counted(other, others)  # the column shows the grid's variants only
        apart = [f"The {label}'s column: {done} of {planned} runs complete (provisional).", ""] if done < planned else []
    lines += [*compact(runs, baseline, variant, other, label), "", *apart, *aggregates(runs, baseline)[0], ""]
    omitted = left_out(runs, baseline)
    lines += [*omitted, ""] if omitted else []
    if lines_of_target:
        lines += [f"Target ({target_wording(spec, baseline)}):", "", *lines_of_target]  # type: ignore[arg-type]
    return "\n".join(lines).rstrip() + "\n"


def report(
    names: list[str],
    storage: str | None,
    baseline: str,
    workers: int,
    png: pathlib.Path | None,
    beside_names: list[str] | None = None,
    cache: dict[tuple, Collected] | None = None,
) -> str:
    """The report's text (and its figures written beside ``png``); ``beside_names``: campaigns of another protocol whose
    ratios to the baseline, per task and over tasks, stand beside these campaigns'; ``cache``: as :func:`read`'s."""
    runs, progress, notes, campaigns = read(names, storage, cache)
    notes = list(notes)  # the cache's stay as read
    protocols = {c.protocol for c in campaigns}
    paper = len(protocols) == 1 and protocols <= set(PUBLISHED)
    lines = [f"Campaigns {', '.join(names)}: {runs_complete(runs, campaigns)[0]}.", ""]
    if not runs:
        return "\n".join(lines + [f"- {note}" for note in notes])
    commits = sorted({r["commit"] for bv in runs.values() for rs in bv.values() for r in rs})
    machines = sorted({r["machine"] for bv in runs.values() for rs in bv.values() for r in rs})
    made = [r for bv in runs.values() for rs in bv.values() for r in rs]
    versions = {name: "/".join(sorted({str(r["versions"].get(name, "?")) for r in made})) for name in made[0]["versions"]}
    notes += left_out(runs, baseline)
    steps = "/".join(f"{s:,}" for s in sorted({c.timesteps for c in campaigns}))
    published = " beside the paper's Table 1 (2M steps, 4M on Ant, 10 seeds)" if paper else ""
    aggregate_lines, normalized = aggregates(runs, baseline)
    zoo = [c for c in campaigns if c.protocol == "zoo"]  # an rl-zoo3 training times its evaluations with itself
    apart = "apart" if not zoo else "included" if len(zoo) == len(campaigns) else "apart, included in protocol zoo's runs"
    sections = [
        [f"Max average return (mean ± half std over seeds, runs in brackets), {steps} env steps, and each variant's "
         f"ratio to {baseline}'s mean{published}:"],
        table(runs, baseline, paper),
        [f"Over tasks: each run's max average return / {baseline}'s mean on its task (95 % stratified-bootstrap CIs "
         f"over the seeds of both); at {baseline}'s CPU time: its best return within {baseline}'s mean training CPU "
         "time (same task and machine):"],
        aggregate_lines,
    ]  # fmt: skip
    if beside_names:
        other, _, _, others = read(beside_names, storage, cache)
        labels = (protocol_label(campaigns), protocol_label(others))
        sections += [[f"Beside campaigns {', '.join(beside_names)} ({labels[1]}): each variant's ratio to {baseline}'s "
                      f"mean max average return (runs of both in brackets) in the {labels[0]}, the {labels[1]} and the "
                      "paper's Table 1:"],
                     beside(runs, other, baseline, labels),  # type: ignore[arg-type]
                     [f"Over tasks in the {labels[1]}:"],
                     aggregates(other, baseline)[0]]  # fmt: skip
        steps = min(c.timesteps for c in (*campaigns, *others))
        sections += [[f"{baseline} in both protocols: its best evaluation within {steps:,} env steps (the shorter "
                      "protocol's budget) and over its whole run, mean ± half std over seeds (runs), and its CPU "
                      "minutes per run (its curves in both: beside.png):"],
                     baseline_beside(runs, other, baseline, labels, steps)]  # fmt: skip
        if png is not None:
            plot_beside(runs, other, baseline, labels, png.with_name("beside.png"))  # type: ignore[arg-type]
    spec, lines_of_target = target_of(runs, campaigns, baseline)
    if lines_of_target:  # where the target's variant and the baseline have runs
        sections += [[f"Against the target for {spec['variant']} ({target_wording(spec, baseline)}):"], lines_of_target]
    if paper:
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
    off_policy = bool(protocols & set(OFF_POLICY))
    diagnostic = local_generalization(runs, "windows" if off_policy else "iterations")
    if diagnostic:
        scored = (OFF_POLICY_SCORED if off_policy else
                  "each new policy's Monte-Carlo returns, before and after the iteration's critic update")  # fmt: skip
        sections += [[f"Local generalization (the paper's Fig. 3b / 8): mean squared error on {scored}, PeVFA "
                      "against a conventional critic trained beside it (over training: local_generalization.png); its "
                      "runs are in the first table only (the extra critic costs time):"], diagnostic]  # fmt: skip
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
            plot_local_generalization(runs, png.with_name("local_generalization.png"), off_policy)
    return "\n".join(lines).rstrip() + "\n"
