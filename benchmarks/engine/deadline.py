"""A time by which the workers stop (``campaign.py run --until``), for a machine lent for a while (a batch job's time
limit, a session): a worker takes a grid point only where the run's expected wall-clock time, less what its
checkpoint has done, ends before the deadline (with ``--fill`` every point, in the campaigns' order, protocol zoo's
apart), and stops a trial still running at the deadline, as SIGTERM does (a checkpoint saved at its next iteration
boundary, the trial marked interrupted, enqueued again by the next ``run`` and going on from that checkpoint where
the machine keeps it). A run's expected time is the longer of the status's two estimates over the campaigns the
workers were given: from complete runs alone, and with running trials' pace (:func:`~engine.results.run_times`,
:func:`~engine.results.scaled_time`; a run's first steps go faster than its whole); a point with no estimate counts
as long as the longest run known (of another campaign, protocol or algorithm), and is taken where no run is known."""

import datetime
import json
import re
import time
from collections.abc import Callable

import numpy as np

from .definitions import Campaign
from .results import collect, run_times, time_of, variant_label

#: (CPU, wall-clock) seconds of a run per task and variant label
Times = dict[tuple[str, str], np.ndarray]
#: The forms ``--until`` takes
UNTIL_FORMS = "HH:MM (the next such local time), YYYY-MM-DDTHH:MM (local), +90m or +2.5h (from now)"
#: Seconds a worker keeps the runs' times it read (a worker with nothing that fits looks again every few seconds)
REREAD_AFTER = 60.0


def parse_until(text: str, now: float | None = None, passed: bool = False) -> float:
    """The deadline ``text`` names, in seconds since the epoch; a ValueError naming the forms for any other text
    and for a date-time that has passed."""
    now = time.time() if now is None else now
    relative = re.fullmatch(r"\+(\d+(?:\.\d+)?)([mh])", text.strip())
    if relative:
        return now + float(relative[1]) * (60.0 if relative[2] == "m" else 3600.0)
    clock = re.fullmatch(r"([01]?\d|2[0-3]):([0-5]\d)", text.strip())
    if clock:
        today = datetime.datetime.fromtimestamp(now).replace(hour=int(clock[1]), minute=int(clock[2]), second=0,
                                                             microsecond=0)  # fmt: skip
        at = today.timestamp()
        return at if at > now else (today + datetime.timedelta(days=1)).timestamp()
    try:
        at = datetime.datetime.fromisoformat(text.strip()).timestamp()
    except ValueError:
        raise ValueError(f"--until {text!r}: give {UNTIL_FORMS}") from None
    if at <= now and not passed:  # a worker started by run takes a deadline that passed as it started
        raise ValueError(f"--until {text!r} has passed (now {datetime.datetime.fromtimestamp(now):%Y-%m-%dT%H:%M})")
    return at


def elapsed(folder) -> float:
    """The wall-clock seconds (training and evaluation) a grid point's checkpoint holds; 0 without one."""
    try:
        state = json.loads((folder / "state.json").read_text())
        return float(state["wall"]) + float(state.get("eval_wall", 0.0))
    except (OSError, ValueError, KeyError):
        return 0.0


class Deadline:
    """The deadline ``at`` (seconds since the epoch) of workers over the campaigns ``names`` in ``storage``."""

    def __init__(self, at: float, names: list[str], storage: str | None) -> None:
        self.at, self.names, self.storage = at, names, storage
        self._read: tuple[float, Times, Times, list[Campaign]] | None = None

    def left(self) -> float:
        return self.at - time.time()

    def times(self) -> tuple[Times, Times, list[Campaign]]:
        """The runs' times from complete runs alone and with running trials' pace, and the campaigns, read from the
        storage at most every ``REREAD_AFTER`` seconds."""
        if self._read is None or time.monotonic() - self._read[0] > REREAD_AFTER:
            runs, progress, _, campaigns = collect(self.names, self.storage)
            self._read = (time.monotonic(), run_times(runs, {}, campaigns), run_times(runs, progress, campaigns), campaigns)
        return self._read[1:]

    def fitting(self, name: str, campaign: Campaign) -> Callable[[tuple[str, str, int]], bool]:
        """Whether a grid point of ``campaign`` (study ``name``) is expected to end before the deadline."""
        complete, extrapolated, campaigns = self.times()
        longest = max((times[1] for times in (*complete.values(), *extrapolated.values())), default=None)

        def fits(point: tuple[str, str, int]) -> bool:
            key = (point[0], variant_label(campaign, point[1], campaigns))
            walls = [times[1] for times in (time_of(complete, key), time_of(extrapolated, key)) if times is not None]
            if not walls and longest is None:
                return True
            expected = max(walls) if walls else longest  # no estimate: as long as the longest run known
            return expected - elapsed(campaign.checkpoint_folder(name, point)) <= self.left()

        return fits
