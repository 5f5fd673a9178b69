"""Workers: each one draws a grid point that no trial holds and trains it as a trial (``training.train``), campaign
after campaign, then waits while others run the last grid points and takes over any whose worker dies; ``run``
recovers the trials of dead workers, starts the worker processes (``benchmarks/campaign.py work``) and shows the
progress."""

import contextlib
import datetime
import importlib
import logging
import os
import pathlib
import random
import signal
import socket
import subprocess
import sys
import time
from collections.abc import Callable
from typing import Any

import gymnasium
import optuna
from optuna.trial import FrozenTrial, TrialState

from .deadline import Deadline
from .definitions import BOX_ACTIONS, ROOT, Campaign
from .storage import (
    boot_id,
    done,
    draw,
    grid_point,
    grid_states,
    open_study,
    pending,
    raised,
    recover,
    running,
    storage_of,
)
from .training import STOP, provenance, train

#: The command line of a worker process (``storage`` knows a live worker by it)
SCRIPT = ROOT / "benchmarks" / "campaign.py"
#: The exit status of a worker stopped by SIGINT or SIGTERM (a shell's for SIGINT)
STOPPED = 130
#: Seconds ``run``, stopped, gives its workers to save a checkpoint, mark their trials and exit before it kills one
#: still running
STOP_GRACE = 120.0
#: Seconds between ``run``'s readings of the grids' progress
PROGRESS_EVERY = 10.0
#: Seconds at most between a worker's looks for a trial to take over while others run the last grid points
WAIT_AT_MOST = 5.0
#: The characters of a training's exception kept in its trial
ERROR_LENGTH = 300


def objective(campaign: Campaign) -> Callable[[optuna.Trial], float]:
    """A trial of ``campaign``: its grid point trained, unless another trial holds it (then pruned as a duplicate)."""

    def run_trial(trial: optuna.Trial) -> float:
        try:
            trial.set_user_attr("interrupted", "")
            trial.set_user_attr("checkpoint", None)  # none saved yet (a database's retry copies its trial's)
            task = trial.suggest_categorical("task", list(campaign.tasks))
            variant = trial.suggest_categorical("variant", list(campaign.variants))
            seed = trial.suggest_categorical("seed", list(campaign.seeds))
            point = (task, variant, seed)
            this = trial.study._storage.get_trial(trial._trial_id)
            others = [t for t in trial.study.get_trials(deepcopy=False) if t.number != trial.number and grid_point(t) == point]
            taken = [t for t in others if _yields(this, t)]
            if taken:  # the grid point is done, or another worker took it at the same moment
                trial.set_user_attr("duplicate_of", taken[0].number)
                raise optuna.TrialPruned()
            trial.set_user_attr("worker", {"host": socket.gethostname(), "boot_id": boot_id(), "pid": os.getpid()})
            trial.set_user_attr("heartbeat", time.time())
            folder = campaign.checkpoint_folder(trial.study.study_name, point)
            head = trial_label(trial.study.study_name, trial.number, point)

            def started(steps: int) -> None:
                news = checkpoint_news(others, steps, folder)
                if news:
                    print(f"{head}: {news}", flush=True)

            # a stop: taken at the training's next iteration boundary, or, once it is complete, after it is stored
            # (rl-zoo3's training of protocol zoo, a process of its own without checkpoints, stops at once)
            with STOP.deferred(campaign.protocol != "zoo"):
                result = train(campaign, task, variant, seed, trial, checkpoint=folder, started=started)
                for key, value in result.items():
                    trial.set_user_attr(key, value)
        except (KeyboardInterrupt, SystemExit):
            trial.set_user_attr("interrupted", "stopped")
            raise
        except optuna.TrialPruned:
            raise
        except Exception as error:  # the status and the report say why it failed
            trial.set_user_attr("error", error_text(error))
            raise
        return result["max_average_return"]

    return run_trial


def checkpoint_news(others: list[FrozenTrial], steps: int, folder: pathlib.Path) -> str:
    """What the log says as a trial starts its grid point, of whose ``others`` trials: the checkpoint it goes on from
    (``steps``), or, where none is (0) and the last of them to save one kept it, that it is not in ``folder`` (another
    machine, a cleared cache, a broken one) and the run starts over; else nothing."""
    if steps:
        return f"goes on from its checkpoint at {steps:,} env steps"
    saved = [t for t in others if t.user_attrs.get("checkpoint")]
    if not saved:
        return ""
    last = max(saved, key=lambda t: t.number)
    checkpoint = last.user_attrs["checkpoint"]
    return (f"trial #{last.number} saved a checkpoint at {checkpoint['steps']:,} env steps on {checkpoint['host']}; "
            f"none to go on from in {folder}: the run starts over")  # fmt: skip


def _yields(trial: FrozenTrial, other: FrozenTrial) -> bool:
    """Whether ``trial`` leaves its grid point to ``other``, a trial of the same point: to a complete one; a new trial
    to a retried one, waiting or running (so that the retry of a dead worker's trial runs, once); between two of the
    same kind, the later to the earlier."""
    if other.state == TrialState.COMPLETE:
        return True
    retried, other_retried = "retry_history" in trial.system_attrs, "retry_history" in other.system_attrs
    if other.state == TrialState.WAITING:
        return other_retried and not retried
    if other.state == TrialState.RUNNING:
        return other_retried > retried or (other_retried == retried and other.number < trial.number)
    return False


def error_text(error: BaseException) -> str:
    """An exception on one line, at most ``ERROR_LENGTH`` characters: its start and its end (a failed rl-zoo3 run's
    is its log's tail, whose last line names the error)."""
    text = " ".join(f"{type(error).__name__}: {error}".split())
    if len(text) <= ERROR_LENGTH:
        return text
    head = ERROR_LENGTH // 3
    return f"{text[:head]} … {text[-(ERROR_LENGTH - head - 3) :]}"


def _ignore(*_: Any) -> None:
    """A handler that ignores its signal. Unlike ``SIG_IGN`` it also takes one already delivered and not yet handled
    (Ctrl-C and ``run``'s SIGTERM at once), where Python would print "Signal 15 ignored due to race condition"."""


def _ignore_stops(exiting: bool = False) -> None:
    """Further SIGINT, SIGTERM and the deadline's alarm (SIGALRM, its timer cancelled) ignored; ``exiting``: by the
    OS (``SIG_IGN``), as Python's exit would put their default action back where a Python handler is set, and a late
    signal would kill the process by it."""
    signal.setitimer(signal.ITIMER_REAL, 0)  # the deadline's alarm: it must not cut a stop short either
    for stop in (signal.SIGINT, signal.SIGTERM, signal.SIGALRM):
        signal.signal(stop, signal.SIG_IGN if exiting else _ignore)


def _stop(*_: Any) -> None:
    """SIGINT, SIGTERM, the deadline: a training goes on to its next iteration boundary and saves a checkpoint there
    (``training.STOP``), then the trial is marked interrupted (and enqueued again by the next ``run``); a second
    signal while it stops is ignored, so that it cannot cut the checkpoint or the marking short."""
    _ignore_stops()
    if not STOP.ask():  # no training that takes it later: at once
        raise KeyboardInterrupt


def work(names: list[str], storage: str | None, stale_after: float = 1800.0, until: float | None = None,
         fill: bool = False) -> None:  # fmt: skip
    """One worker (:func:`work_on_all`); stopped (SIGINT, SIGTERM, the deadline), it exits with ``STOPPED`` and no
    traceback."""
    logging.getLogger("optuna.study._optimize").addFilter(_without_stop_traceback)  # its one-line warning stays
    try:
        work_on_all(names, storage, stale_after, until, fill)
    except KeyboardInterrupt:
        _ignore_stops(exiting=True)
        raise SystemExit(STOPPED) from None


def _without_stop_traceback(record: logging.LogRecord) -> bool:
    """Optuna's warning on a stopped trial without its traceback (the training's stack where the stop reached it)."""
    if record.exc_info and record.exc_info[0] is KeyboardInterrupt:
        record.exc_info = None
    return True


def work_on_all(names: list[str], storage: str | None, stale_after: float = 1800.0, until: float | None = None,
                fill: bool = False) -> None:  # fmt: skip
    """Trials of the campaigns one after another, each campaign's grid before the next one's; then, while other
    workers run the last grid points, it waits, and runs any whose worker dies. With ``until`` (seconds since the
    epoch) only grid points expected to end before it (a campaign's others left to the next one's; with ``fill``
    every point, as without it, protocol zoo's apart), and at ``until`` it stops as by SIGTERM, a training with a
    checkpoint to go on from (:mod:`~engine.deadline`)."""
    signal.signal(signal.SIGTERM, _stop)
    signal.signal(signal.SIGINT, _stop)
    deadline = None if until is None else Deadline(until, names, storage)
    if deadline is not None:
        signal.signal(signal.SIGALRM, _stop)
        signal.setitimer(signal.ITIMER_REAL, max(deadline.left(), 0.001))
    optuna.logging.set_verbosity(optuna.logging.WARNING)
    provenance()  # the code this process runs
    studies = [(name, *open_study(name, storage_of(name, storage))) for name in names]

    def limit(campaign: Campaign) -> Deadline | None:
        """The deadline a campaign's points must end before: none with ``fill`` (a stop keeps the run's work), but
        for protocol zoo, whose rl-zoo3 training keeps no checkpoint."""
        return None if fill and campaign.protocol != "zoo" else deadline

    for name, study, campaign in studies:
        work_on(name, study, campaign, limit(campaign))
    delay = 0.5
    while any(running(study, campaign) for _, study, campaign in studies):
        if STOP.asked:  # asked as a training ended
            raise KeyboardInterrupt
        time.sleep(delay)
        delay = min(2 * delay, WAIT_AT_MOST)
        for name, study, campaign in studies:
            recover(study, campaign, stale_after)
            work_on(name, study, campaign, limit(campaign))


def trial_label(name: str, number: int, point: tuple) -> str:
    """How the log names a trial: ``<campaign> #<trial> <task> <variant> seed <seed>``."""
    task, variant, seed = point
    return f"{name} #{number} {task} {variant} seed {seed}"


def work_on(name: str, study: optuna.Study, campaign: Campaign, deadline: Deadline | None = None) -> None:
    """The campaign's grid points, trial after trial (with a ``deadline``, only those expected to end before it)."""
    total = len(campaign.grid)

    def announce(study: optuna.Study, trial: FrozenTrial) -> None:
        point = grid_point(trial) or ("(no parameters)", "", "")
        if trial.state == TrialState.COMPLETE:
            a = trial.user_attrs
            line = (f"max average return {a['max_average_return']:.1f}, final {a['final_return']:.1f}, "
                    f"{a['steps_per_cpu_second']:.0f} steps/CPU-s, {a['cpu_seconds'] / 60:.1f} CPU-min "
                    f"(+{a['eval_cpu_seconds'] / 60:.1f} evaluating), {a['wall_seconds'] / 60:.1f} wall-min")  # fmt: skip
        else:
            line = trial.state.name
        print(f"[{done(study, campaign)}/{total}] {trial_label(name, trial.number, point)}: {line}", flush=True)

    rng = random.Random()  # seeded from the OS: workers draw apart
    while pending(study, campaign):
        if STOP.asked:  # asked as a training ended: its trial is complete, the worker stops before the next one
            raise KeyboardInterrupt
        if not draw(study, campaign, rng, deadline and deadline.fitting(name, campaign)):
            return  # nothing left that ends before the deadline (or another worker took the last point)
        study.optimize(objective(campaign), n_trials=1, catch=(Exception,), callbacks=[announce], gc_after_trial=True)


def unmakeable(protocol: str, tasks: tuple[str, ...] | list[str]) -> list[str]:
    """Why each of ``tasks`` cannot be trained in ``protocol`` here: its env cannot be made (a missing dependency:
    MuJoCo, Box2D; an unknown id), or the protocol needs a Box action space it lacks. Each env is made once."""
    problems = []
    for task in tasks:
        try:
            if protocol == "zoo":  # rl-zoo3's own envs, as its training registers them
                importlib.import_module("rl_zoo3.import_envs")
            env = gymnasium.make(task)
            space = env.action_space
            env.close()
        except Exception as error:
            problems.append(f"{task}: {type(error).__name__}: {error}")
            continue
        if protocol in BOX_ACTIONS and not isinstance(space, gymnasium.spaces.Box):
            problems.append(f"{task}: protocol {protocol!r} needs a Box action space, the task's is {space}")
    return problems


def check_tasks(studies: list[tuple[optuna.Study, Campaign]]) -> None:
    """Each task with a grid point that will train (never started, enqueued, or running: it may be taken over)
    checked by :func:`unmakeable`, so that a missing dependency stops ``run`` with its reason before any trial fails
    of it."""
    problems, seen = [], set()
    will_run = (TrialState.WAITING, TrialState.RUNNING)
    for study, campaign in studies:
        for (task, _, _), trials in grid_states(study, campaign).items():
            if (task, campaign.protocol) in seen or (trials and trials[-1].state not in will_run):
                continue
            seen.add((task, campaign.protocol))
            problems += [f"  {study.study_name}: {problem}" for problem in unmakeable(campaign.protocol, [task])]
    if problems:
        raise SystemExit("These tasks cannot be trained on this machine, so no worker started (the benchmarks' "
                         'dependencies: pip install -e ".[zoo,mujoco,box2d,diagnostics]"):\n'
                         + "\n".join(problems))  # fmt: skip


def run(
    names: list[str],
    storage: str | None,
    workers: int,
    stale_after: float,
    retry_raised: bool = False,
    until: float | None = None,
    fill: bool = False,
) -> None:
    """Recover the trials of dead workers (with ``retry_raised``, the grid points whose training raised too), check
    that the tasks left can be made, start ``workers`` worker processes over the campaigns in order (with ``until``,
    a deadline, and ``fill``: :mod:`~engine.deadline`) and show the grids' progress."""
    studies = []
    for name in names:
        study, campaign = open_study(name, storage_of(name, storage))
        retried = recover(study, campaign, stale_after, retry_raised)
        if retried:
            why = "were interrupted or their worker is gone" + (", or their training raised" if retry_raised else "")
            print(f"{name}: trials {retried} {why}: enqueued again", flush=True)
        print(f"{name}: {done(study, campaign)}/{len(campaign.grid)} grid points complete, "
              f"{pending(study, campaign)} waiting", flush=True)  # fmt: skip
        studies.append((study, campaign))
        if failed(study, campaign):
            print(f"{name}: {failed_text(study, campaign)}", flush=True)
    check_tasks(studies)
    command = [sys.executable, str(SCRIPT), "work", "--campaign", *names]
    command += ["--stale-after", str(stale_after)]
    command += ["--storage", storage] if storage else []
    command += ["--until", datetime.datetime.fromtimestamp(until).astimezone().isoformat()] if until is not None else []
    command += ["--fill"] if fill else []
    processes = [subprocess.Popen(command) for _ in range(workers)]

    def stop(*_: Any) -> None:
        raise KeyboardInterrupt

    signal.signal(signal.SIGTERM, stop)
    from tqdm import tqdm

    def complete() -> int:
        return sum(done(study, campaign) for study, campaign in studies)

    total = sum(len(campaign.grid) for _, campaign in studies)
    try:
        with tqdm(total=total, initial=complete(), desc=" ".join(names), unit="trial", disable=None) as bar:
            while any(process.poll() is None for process in processes):
                wait_any(processes, PROGRESS_EVERY)
                bar.update(complete() - bar.n)
    except KeyboardInterrupt:  # Ctrl-C (it reached the workers too) or SIGTERM
        stop_workers(processes)
    codes = [process.wait() for process in processes]
    at = "" if until is None else f" at {datetime.datetime.fromtimestamp(until):%Y-%m-%d %H:%M}"
    reached = until is not None and time.time() >= until
    if codes and STOPPED in codes and set(codes) <= {0, STOPPED} and not reached:
        raise SystemExit(f"{' '.join(names)}: stopped; the same run command goes on (a stopped trial from its checkpoint)")
    if any(code not in (0, STOPPED) for code in codes):
        raise SystemExit(f"{' '.join(names)}: workers exited with {codes}")
    unfinished = [f"{name}: {failed_text(study, campaign)}" for name, (study, campaign) in zip(names, studies)
                  if failed(study, campaign)]  # fmt: skip
    if unfinished:
        raise SystemExit("\n".join(unfinished))
    left = sum(len(campaign.grid) - done(study, campaign) for study, campaign in studies)
    if left and until is not None:  # the deadline came, or nothing more was expected to end before it: a success
        why = "reached" if reached else "near: none of them expected to end before it"
        print(f"{left} grid points left for a later run (the same command; a stopped trial goes on from its "
              f"checkpoint): the deadline{at} {why}", flush=True)  # fmt: skip


def wait_any(processes: list[subprocess.Popen], seconds: float) -> None:
    """Until ``seconds`` have passed or one more process has exited: ``run`` ends as soon as its workers do."""

    def alive() -> int:
        return sum(process.poll() is None for process in processes)

    deadline, n_alive = time.monotonic() + seconds, alive()
    while time.monotonic() < deadline and alive() == n_alive > 0:
        time.sleep(0.1)


def stop_workers(processes: list[subprocess.Popen]) -> None:
    """The workers told to stop (SIGTERM; one already stopping ignores it) and given ``STOP_GRACE`` seconds to save a
    checkpoint, mark their trials and exit; one still running then is killed (the next ``run`` recovers its trial, its
    worker gone, and goes on from its last checkpoint)."""
    _ignore_stops()  # a second Ctrl-C or kill cannot cut the wait short
    with contextlib.suppress(OSError):  # stderr may have gone with the terminal or the pipe
        print(f"stopping: the workers save a checkpoint and mark their trials (at most {STOP_GRACE:.0f} s)",
              file=sys.stderr, flush=True)  # fmt: skip
    for process in processes:
        if process.poll() is None:
            process.send_signal(signal.SIGTERM)
    deadline = time.monotonic() + STOP_GRACE
    while time.monotonic() < deadline and any(process.poll() is None for process in processes):
        time.sleep(0.5)
    for process in processes:
        if process.poll() is None:
            process.kill()
    _ignore_stops(exiting=True)  # run exits next


def failed(study: optuna.Study, campaign: Campaign) -> int:
    """Grid points without a complete trial whose latest trial's training raised."""
    return sum(bool(trials) and raised(trials[-1]) for trials in grid_states(study, campaign).values())


def failed_text(study: optuna.Study, campaign: Campaign) -> str:
    return (f"{failed(study, campaign)} grid points failed: their training raised (the status shows each one's "
            "exception; the same command with --retry-raised trains them again once the cause is mended)")  # fmt: skip
