"""Iterations of whole episodes (``rollout_episodes``, the authors' rollouts): one env collects episodes until
``rollout_episodes`` of them ended or ``n_steps`` steps were collected, whichever comes first, always finishing the
episode under way. The rollout buffer grows while it collects and is cut to what was collected; the historical
critic updates are counted per episode, as the authors' code runs them at each episode's end.
"""

import numpy as np
from stable_baselines3.common.buffers import DictRolloutBuffer, RolloutBuffer

#: The rollout buffer's fields of one row per step and env (observations may be a dict of such arrays)
_FIELDS = ("observations", "actions", "rewards", "returns", "episode_starts", "values", "log_probs", "advantages")


def resize(buffer: RolloutBuffer | DictRolloutBuffer, size: int) -> None:
    """Cut the buffer's arrays to their first ``size`` rows, or extend them with zeros to ``size`` rows; the buffer
    reads as full at that size once it holds that many (``pos``), as SB3's ``get`` and GAE need."""

    def resized(array: np.ndarray) -> np.ndarray:
        if size <= len(array):
            return array[:size]
        return np.concatenate([array, np.zeros((size - len(array), *array.shape[1:]), dtype=array.dtype)])

    for name in _FIELDS:
        value = getattr(buffer, name)
        setattr(buffer, name, {k: resized(v) for k, v in value.items()} if isinstance(value, dict) else resized(value))
    buffer.buffer_size = size
    buffer.full = buffer.pos >= size


def episode_lengths(episode_starts: np.ndarray) -> np.ndarray:
    """Lengths of the episodes of a rollout of whole episodes (one env): ``episode_starts`` ``(n_steps,)`` or
    ``(n_steps, 1)``, its first row the first step of an episode, its last row the last step of one."""
    starts = np.flatnonzero(np.asarray(episode_starts).reshape(-1))
    starts = np.concatenate([[0], starts[starts > 0]])
    return np.diff(np.concatenate([starts, [np.asarray(episode_starts).size]]))


def historical_updates(lengths: np.ndarray, end_step: int, train_freq: int, learning_starts: int) -> np.ndarray:
    """Historical critic updates at the end of each episode, as the authors' code counts them: an episode that ends
    after more than ``learning_starts`` env steps in all gets one update per multiple of ``train_freq`` that the
    step counter crossed during it, none before.

    :param lengths: The rollout's episode lengths, in order (:func:`episode_lengths`)
    :param end_step: The env steps in all at the end of the rollout
    """
    ends = end_step - np.concatenate([np.cumsum(lengths[::-1])[::-1][1:], [0]])
    updates = ends // train_freq - (ends - lengths) // train_freq
    return np.where(ends > learning_starts, updates, 0)
