"""A campaign's study: its storage (a journal file, or a database for many machines), the study with the campaign's
definition stored in it, each grid point's trials, and the retries: the RUNNING trials of dead workers failed and their
grid points enqueued again, at most ``MAX_RETRY`` times for the deaths of a worker; grid points drawn for workers."""

import pathlib
import random
import socket
import time
import warnings
from collections.abc import Callable
from typing import Any

import optuna
import sqlalchemy
from optuna.storages import JournalStorage, RDBStorage
from optuna.storages.journal import JournalFileBackend
from optuna.trial import FrozenTrial, TrialState

from .definitions import CAMPAIGN_DIR, CAMPAIGNS, Campaign

try:  # Optuna >= 4.9's names of the callback that enqueues a stale trial again, and of RDBStorage's argument
    from optuna.storages import RetryHeartbeatStaleTrialCallback

    RETRY_ARGUMENT = "heartbeat_stale_trial_callback"
except ImportError:  # pragma: no cover
    from optuna.storages import RetryFailedTrialCallback as RetryHeartbeatStaleTrialCallback

    RETRY_ARGUMENT = "failed_trial_callback"

warnings.filterwarnings("ignore", category=optuna.exceptions.ExperimentalWarning)

#: A retried trial is enqueued again at most this many times
MAX_RETRY = 3


def storage_of(campaign: str, storage: str | None = None) -> optuna.storages.BaseStorage:
    """``storage``: a database URL (``postgresql://...``, ``sqlite:///...``), a journal file's path, or None for
    ``benchmarks/campaigns/<campaign>.journal``."""
    if storage and "://" in storage:
        for attempt in range(3):  # machines starting together race to create the schema: the losers read it
            try:
                return RDBStorage(
                    storage,
                    heartbeat_interval=60,
                    grace_period=600,
                    **{RETRY_ARGUMENT: RetryHeartbeatStaleTrialCallback(max_retry=MAX_RETRY)},
                )
            except (sqlalchemy.exc.IntegrityError, sqlalchemy.exc.ProgrammingError):  # a duplicate row, or table
                if attempt == 2:
                    raise
                time.sleep(1.0 + attempt)
    path = journal_path(campaign, storage)
    path.parent.mkdir(parents=True, exist_ok=True)
    return JournalStorage(JournalFileBackend(str(path)))


def journal_path(campaign: str, storage: str | None = None) -> pathlib.Path:
    """The journal file of a campaign: ``storage`` (not a database URL), or the repository's."""
    return pathlib.Path(storage) if storage else CAMPAIGN_DIR / f"{campaign}.journal"


def is_stored(campaign: str, storage: str | None = None) -> bool:
    """Whether the storage holds the campaign's study (a journal file that does not exist is not created)."""
    if not (storage and "://" in storage) and not journal_path(campaign, storage).exists():
        return False
    return campaign in {summary.study_name for summary in optuna.get_all_study_summaries(storage_of(campaign, storage))}


def stored_names(storage: str | None = None) -> list[str]:
    """The campaigns a storage holds: a database's studies, a journal file's, or the repository's journal files."""
    if storage and "://" in storage:
        return optuna.get_all_study_names(storage_of("", storage))
    if storage:
        return optuna.get_all_study_names(storage_of("", storage)) if pathlib.Path(storage).exists() else []
    return sorted(path.stem for path in CAMPAIGN_DIR.glob("*.journal"))


def open_study(
    name: str, storage: optuna.storages.BaseStorage, given: Campaign | None = None
) -> tuple[optuna.Study, Campaign]:
    """The campaign's study, created with ``given`` (or ``CAMPAIGNS[name]``) and its definition stored;
    a stored campaign is never redefined: a different definition is a ValueError."""
    expected = given or CAMPAIGNS.get(name)
    existing = {summary.study_name for summary in optuna.get_all_study_summaries(storage)}
    if name not in existing and expected is None:
        raise ValueError(f"Unknown campaign {name!r}: one of {sorted(CAMPAIGNS)}, or give campaign.py --protocol, "
                         "--tasks, --variants, --seeds and --timesteps to define a new one")  # fmt: skip
    if name in existing:
        study = optuna.load_study(study_name=name, storage=storage)
    else:  # load_if_exists: another machine may create it at the same moment
        study = optuna.create_study(study_name=name, storage=storage, direction="maximize", load_if_exists=True)
    stored = study.user_attrs.get("campaign")
    if stored is None:  # new (or created by a machine that has not stored its definition yet: the same command's)
        if expected is None:
            raise ValueError(f"Campaign {name!r} has no definition yet: give it (--protocol, --tasks, ...)")
        study.set_user_attr("campaign", expected.definition())
        stored = expected.definition()
    campaign = Campaign.from_definition(stored)
    expected = expected or campaign  # a campaign of one's own: its variants' settings as this code defines them
    if expected.definition() != stored:
        given = expected.definition()
        changed = ", ".join(f"{key} {stored.get(key)!r} (given: {given.get(key)!r})"
                            for key in dict.fromkeys([*stored, *given]) if stored.get(key) != given.get(key))  # fmt: skip
        raise ValueError(f"Campaign {name!r} was started with {changed}: a campaign's definition never changes; "
                         "start one under another name (or, to start over, delete its study from the storage)")  # fmt: skip
    study.sampler = optuna.samplers.GridSampler(campaign.search_space)  # the grid; workers enqueue its points (draw)
    return study, campaign


def grid_point(trial: FrozenTrial) -> tuple[str, str, int] | None:
    params = trial.params or trial.system_attrs.get("fixed_params", {})
    return (params["task"], params["variant"], params["seed"]) if {"task", "variant", "seed"} <= set(params) else None


def grid_states(study: optuna.Study, campaign: Campaign) -> dict[tuple[str, str, int], list[FrozenTrial]]:
    """Every grid point's trials, in order."""
    states: dict[tuple[str, str, int], list[FrozenTrial]] = {point: [] for point in campaign.grid}
    for trial in study.get_trials(deepcopy=False):
        point = grid_point(trial)
        if point in states:
            states[point].append(trial)
    return states


def _interrupted(trial: FrozenTrial, database: bool = False) -> bool:
    """A failed trial that was stopped or lost its worker; on a journal also one that kept no reason (a stop that
    reached it as it marked itself, or a trial of an older version). On a database such a trial is one that Optuna's
    heartbeat failed, and Optuna's callback retries it."""
    return trial.state == TrialState.FAIL and bool(trial.user_attrs.get("interrupted") or not (database or raised(trial)))


def on_database(study: optuna.Study) -> bool:
    """Whether the study lives in a database (Optuna wraps an RDBStorage in a cache), where Optuna's heartbeat fails
    the trials of dead workers and enqueues them again."""
    return isinstance(getattr(study._storage, "_backend", study._storage), RDBStorage)


def raised(trial: FrozenTrial) -> bool:
    """Whether a failed trial's training raised (it kept its exception)."""
    return trial.state == TrialState.FAIL and not trial.user_attrs.get("interrupted") and "error" in trial.user_attrs


def _alive(worker: dict[str, Any], stale_after: float, heartbeat: float | None) -> bool:
    """Whether the worker of a RUNNING trial still runs: its process on this machine, else a recent heartbeat."""
    if worker.get("host") == socket.gethostname() and worker.get("boot_id") == boot_id():
        try:
            cmdline = pathlib.Path(f"/proc/{worker['pid']}/cmdline").read_bytes()
        except OSError:
            return False
        return b"campaign.py\x00work" in cmdline  # that process, not another one under a reused pid
    return heartbeat is not None and time.time() - heartbeat < stale_after


def boot_id() -> str:
    try:
        return pathlib.Path("/proc/sys/kernel/random/boot_id").read_text().strip()
    except OSError:
        return ""


def deaths(latest: FrozenTrial, trials: dict[int, FrozenTrial]) -> int:
    """How many times the worker of a grid point died (a trial failed as "worker gone"), over ``latest`` and the
    trials it retries (``trials``: by number); deliberate stops (SIGINT, SIGTERM) do not count."""
    attempts = [*latest.system_attrs.get("retry_history", []), latest.number]
    return sum(trials[n].user_attrs.get("interrupted") == "worker gone" for n in attempts if n in trials)


def retried_enough(latest: FrozenTrial, trials: dict[int, FrozenTrial]) -> bool:
    """Whether an interrupted grid point is left failed: its worker died more than ``MAX_RETRY`` times."""
    return _interrupted(latest) and deaths(latest, trials) > MAX_RETRY


def recover(study: optuna.Study, campaign: Campaign, stale_after: float = 1800.0, retry_raised: bool = False) -> list[int]:
    """Fail the RUNNING trials of dead workers (journal storage: the process on this machine is gone, else no
    heartbeat for ``stale_after`` seconds; a database: Optuna's heartbeat, whose callback enqueues the retry) and
    enqueue each grid point whose latest trial was interrupted again, unless its worker died more than ``MAX_RETRY``
    times; with ``retry_raised``, each whose latest training raised too (once its cause is mended). Returns the
    numbers of the trials retried."""
    storage, database = study._storage, on_database(study)
    if database:
        optuna.storages.fail_stale_trials(study)
    by_number = {t.number: t for t in study.get_trials(deepcopy=False)}
    retried = []
    for trials in grid_states(study, campaign).values():
        if any(t.state in (TrialState.COMPLETE, TrialState.WAITING) for t in trials):
            continue
        for trial in trials:
            if trial.state != TrialState.RUNNING or database:
                continue
            started = trial.datetime_start.timestamp() if trial.datetime_start else None
            if not _alive(trial.user_attrs.get("worker", {}), stale_after, trial.user_attrs.get("heartbeat", started)):
                storage.set_trial_user_attr(trial._trial_id, "interrupted", "worker gone")
                storage.set_trial_state_values(trial._trial_id, TrialState.FAIL)
        trials = [storage.get_trial(t._trial_id) for t in trials if t.state != TrialState.PRUNED]  # not duplicates
        if not trials or any(t.state == TrialState.RUNNING for t in trials):
            continue
        latest = trials[-1]
        history = latest.system_attrs.get("retry_history", [])
        again = _interrupted(latest, database)
        again = again and not retried_enough(latest, {**by_number, **{t.number: t for t in trials}})
        if again or (retry_raised and raised(latest)):
            # Optuna's retry (as RetryHeartbeatStaleTrialCallback enqueues it), without the failed run's attributes
            enqueue(study, grid_point(latest), failed_trial=latest.system_attrs.get("failed_trial", latest.number),
                    retry_history=[*history, latest.number])  # fmt: skip
            retried.append(latest.number)
    return retried


def enqueue(study: optuna.Study, point: tuple[str, str, int], **system_attrs: Any) -> None:
    """A waiting trial of ``point`` with fixed parameters, as ``Study.enqueue_trial`` makes it: the GridSampler gives
    such a trial no grid id, so it never marks another grid point as visited (a trial that draws its parameters from
    the sampler, as retries did before, takes the id of its number and left that id's point to random draws)."""
    params = dict(zip(("task", "variant", "seed"), point))
    study.add_trial(optuna.create_trial(state=TrialState.WAITING, system_attrs={"fixed_params": params, **system_attrs}))


def draw(
    study: optuna.Study, campaign: Campaign, rng: random.Random, fits: Callable[[tuple[str, str, int]], bool] | None = None
) -> bool:
    """Enqueue a grid point that no trial holds, drawn at random (each worker its own draw, so that workers starting
    together rarely take the same one), unless a trial waits already (a retry first). With ``fits``, only a point
    it accepts, and a waiting trial only where it accepts that trial's point (the first one waiting, which Optuna
    starts next). Whether a trial waits to start now."""
    states = grid_states(study, campaign)
    waiting = sorted((t.number, point) for point, trials in states.items() for t in trials if t.state == TrialState.WAITING)
    if waiting:
        return fits is None or fits(waiting[0][1])
    free = [point for point, trials in states.items() if not trials and (fits is None or fits(point))]
    if free:
        enqueue(study, rng.choice(free))
    return bool(free)


def pending(study: optuna.Study, campaign: Campaign) -> int:
    """Grid points that no worker has started and that wait for one (never run, or enqueued again)."""
    count = 0
    for trials in grid_states(study, campaign).values():
        if not trials or any(t.state == TrialState.WAITING for t in trials):
            count += 1
    return count


def done(study: optuna.Study, campaign: Campaign) -> int:
    """Grid points with a complete trial."""
    return sum(any(t.state == TrialState.COMPLETE for t in trials) for trials in grid_states(study, campaign).values())


def running(study: optuna.Study, campaign: Campaign) -> int:
    """Grid points without a complete trial whose latest trial runs."""
    count = 0
    for trials in grid_states(study, campaign).values():
        trials = [t for t in trials if t.state != TrialState.PRUNED]  # not duplicates
        complete = any(t.state == TrialState.COMPLETE for t in trials)
        count += bool(trials) and trials[-1].state == TrialState.RUNNING and not complete
    return count
