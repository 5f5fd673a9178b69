"""Checkpoints with their history: SB3's ``CheckpointCallback`` names, rl-zoo3's ``--save-freq`` and ``-i``.

A checkpoint ``<prefix>_<steps>_steps.zip`` of a PeVFA model is written with its history beside it, under the name
SB3's ``CheckpointCallback`` gives a replay buffer (``<prefix>_replay_buffer_<steps>_steps.pkl``), and loading the
checkpoint finds that history again: :func:`enable_history_checkpoints`, :func:`checkpoint_history`.
"""

import os
import pathlib
import re
import sys
import warnings
from typing import Any

from stable_baselines3.common.callbacks import BaseCallback, CallbackList, CheckpointCallback
from stable_baselines3.common.type_aliases import MaybeCallback

from sb3_pevfa.pevfa.history import PolicyHistory, latest_recorded

_CHECKPOINT = re.compile(r"(?P<prefix>.+)_(?P<steps>\d+)_steps(\.zip)?")


def _callbacks(callback: MaybeCallback) -> list[BaseCallback]:
    """Every callback in ``callback`` (a list, a ``CallbackList`` or one), nested ones included."""
    if callback is None:
        return []
    if isinstance(callback, list):
        return [c for item in callback for c in _callbacks(item)]
    if isinstance(callback, CallbackList):
        return [callback, *_callbacks(callback.callbacks)]
    nested = getattr(callback, "callback", None)  # EventCallback's child
    return [callback, *(_callbacks(nested) if isinstance(nested, BaseCallback) else [])]


def enable_history_checkpoints(callback: MaybeCallback) -> None:
    """Make every ``CheckpointCallback`` in ``callback`` save the history with each checkpoint (its
    ``save_replay_buffer``; rl-zoo3's ``--save-freq`` creates one without it)."""
    for item in _callbacks(callback):
        if isinstance(item, CheckpointCallback):
            item.save_replay_buffer = True


def checkpoint_history(model_path: str | pathlib.Path) -> pathlib.Path | None:
    """The history saved with the checkpoint ``model_path`` (``..._<steps>_steps[.zip]``), if it exists."""
    path = pathlib.Path(model_path)
    match = _CHECKPOINT.fullmatch(path.name)
    if match is None:
        return None
    history = path.with_name(f"{match['prefix']}_replay_buffer_{match['steps']}_steps.pkl")
    return history if history.exists() else None


def histories_of_the_moment(directory: pathlib.Path, num_timesteps: int) -> list[pathlib.Path]:
    """The checkpoint histories in ``directory`` saved at ``num_timesteps`` (the moment of a model loaded from one of
    them), of any run's prefix."""
    return sorted(directory.glob(f"*_replay_buffer_{num_timesteps}_steps.pkl"))


def path_of_the_moment(path: Any, num_timesteps: int, what: str = "the history", history_of: Any = None) -> Any:
    """What to load for a model at ``num_timesteps`` that asks for ``path``: rl-zoo3's ``-i`` asks for the run's final
    ``replay_buffer.pkl`` also for a checkpoint, so where that file holds policies recorded after the model, and SB3's
    ``CheckpointCallback`` saved one beside it at ``num_timesteps``, that one, with a warning that names it; else
    ``path`` (also where several runs' checkpoints in that folder were saved at that step: which one is this model's
    is not known, and the asked file's history then warns that it comes from after the model).

    :param history_of: The history file saved with a file to load (default: the file itself)
    """
    if not isinstance(path, (str, pathlib.Path)):
        return path
    asked = pathlib.Path(path)
    asked = asked if asked.suffix == ".pkl" else asked.with_name(asked.name + ".pkl")  # SB3 adds .pkl where missing
    moments = histories_of_the_moment(asked.parent, num_timesteps)
    if not moments:
        return path
    if asked in moments:  # the checkpoint's own file, under the name it was saved with
        return asked
    latest = latest_recorded((history_of or (lambda file: file))(asked))
    if latest is not None and latest <= num_timesteps:  # the asked file is of the model's moment (or before it)
        return path
    if len(moments) > 1:
        names = ", ".join(m.name for m in moments)
        warnings.warn(
            f"Several checkpoints in {asked.parent} were saved at {num_timesteps} steps ({names}): {asked} is loaded as "
            f"asked; to go on from a checkpoint, load {what} saved with it by its name",
            stacklevel=_user_stacklevel(),
        )
        return path
    warnings.warn(
        f"Loading {what} saved with the checkpoint at {num_timesteps} steps: {moments[0]} ({asked} holds policies "
        "recorded after this model)",
        stacklevel=_user_stacklevel(),
    )
    return moments[0]


def warn_if_newer(history: PolicyHistory, num_timesteps: int, path: Any) -> None:
    """Warn where ``history`` holds policies recorded after ``num_timesteps`` (e.g. a run's final history loaded
    beside one of its checkpoints), at the user's line that asked for it."""
    latest = history.latest_recorded
    if latest > num_timesteps:
        warnings.warn(
            f"The history {path} holds policies recorded up to {latest} steps, this model is at {num_timesteps}: it "
            "is not the history of this model's moment (for a checkpoint, load the history saved with it: "
            "<prefix>_replay_buffer_<steps>_steps.pkl)",
            stacklevel=_user_stacklevel(),
        )


def _user_stacklevel() -> int:
    """``warnings.warn``'s stacklevel, called from the function calling this one, of the first frame outside the
    package (the user's call, however many of the package's methods lie between)."""
    package = str(pathlib.Path(__file__).resolve().parents[1]) + os.sep
    frame, level = sys._getframe(2), 2
    while frame is not None and str(pathlib.Path(frame.f_code.co_filename).resolve()).startswith(package):
        frame, level = frame.f_back, level + 1
    return level
