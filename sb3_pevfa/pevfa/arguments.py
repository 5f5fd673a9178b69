"""The PeVFA arguments that every PeVFA algorithm's constructor takes: their names, and their checks."""

from collections.abc import Generator
from contextlib import contextmanager
from typing import Any

import numpy as np
from gymnasium import spaces

from sb3_pevfa.common.checks import is_int
from sb3_pevfa.pevfa.critics import CRITIC_DEFAULTS, EARLIER_CRITIC
from sb3_pevfa.pevfa.representations import REPRESENTATIONS

#: Valid values of ``update_order``.
UPDATE_ORDERS = ("joint", "critic_first")
#: Valid values of ``history_targets``: the rollout's value targets, or lambda-returns recomputed with the current critic
HISTORY_TARGETS = ("rollout", "recomputed")
#: Valid values of ``history_normalization``: under ``VecNormalize``, the history in today's statistics, or as its
#: rollout saw it (stale once the statistics move; what PeVFA did before 0.1.0, kept as an ablation)
HISTORY_NORMALIZATIONS = ("current", "rollout")
#: Valid values of ``critic_minibatches``: SB3's (``batch_size`` each, the last one shorter), or the authors' (N // (N //
#: batch_size) samples each, the remainder left out of the epoch)
CRITIC_MINIBATCHES = ("sb3", "even")
#: The PeVFA arguments of every PeVFA algorithm's constructor (documented there).
PEVFA_ARGUMENTS = (
    "representation",
    "embedding_dim",
    "representation_kwargs",
    "n_state_action_pairs",
    "representation_objectives",
    "objective_kwargs",
    "critic_learning_rate",
    "update_order",
    "value_target_lambda",
    "history_buffer_size",
    "history_max_policies",
    "history_batch_size",
    "history_batch_policies",
    "history_train_freq",
    "history_learning_starts",
    "history_targets",
    "history_target_refresh",
    "history_normalization",
    "rollout_encoder_gradient",
    "fast_path",
    "flush_denormal",
    "rollout_episodes",
    "bootstrap_truncated",
    "train_on_clipped_actions",
    "critic_minibatches",
)
#: The paper's schedule of the historical critic updates (App. F.1: 64 uniform samples per 10 environment steps) and
#: its end-to-end encoder, which PPOPeVFA's defaults trade for a cheaper one: ``PPOPeVFA(..., **PAPER_SCHEDULE)``
PAPER_SCHEDULE = dict(history_batch_size=64, history_batch_policies=None, history_train_freq=10, rollout_encoder_gradient=True)
#: The PeVFA arguments that build the policy: the class adds them to ``policy_kwargs`` (and CRITIC_DEFAULTS where
#: they are not given)
ADDED_POLICY_KWARGS = PEVFA_ARGUMENTS[:6]
_SUPPORTED_OBSERVATION_SPACES = (spaces.Box, spaces.Discrete, spaces.MultiDiscrete, spaces.MultiBinary)


def pevfa_policy_kwargs(policy_kwargs: dict[str, Any] | None, arguments: dict[str, Any]) -> dict[str, Any]:
    """``policy_kwargs`` with the policy's PeVFA arguments added (they may not be given twice), and the critic's
    embedding stream spelled out (:data:`~sb3_pevfa.pevfa.critics.CRITIC_DEFAULTS` where not given), so that it is
    saved with the model."""
    ours = {name: arguments[name] for name in ADDED_POLICY_KWARGS}
    policy_kwargs = dict(policy_kwargs or {})
    clash = sorted(set(policy_kwargs) & set(ours))
    if clash:
        raise ValueError(f"Pass {clash} as arguments of the algorithm, not in policy_kwargs")
    return {**CRITIC_DEFAULTS, **policy_kwargs, **ours}


def with_saved_critic(policy_kwargs: dict[str, Any]) -> dict[str, Any]:
    """The ``policy_kwargs`` of a loaded model: one saved without the critic's keys (before 0.1.0 wrote them)
    has the earlier stream (:data:`~sb3_pevfa.pevfa.critics.EARLIER_CRITIC`), whatever the default is today."""
    return {**EARLIER_CRITIC, **policy_kwargs}


@contextmanager
def action_space_errors_as_type_errors() -> Generator[None, None, None]:
    """SB3 asserts on unsupported action spaces: raise a precise TypeError instead."""
    try:
        yield
    except AssertionError as error:
        if "action spaces" in str(error):
            raise TypeError(str(error)) from error
        raise


def check_observation_space(observation_space: spaces.Space, algorithm: str) -> None:
    subspaces = observation_space.spaces.values() if isinstance(observation_space, spaces.Dict) else [observation_space]
    for space in subspaces:
        if not isinstance(space, _SUPPORTED_OBSERVATION_SPACES):
            raise TypeError(
                f"{algorithm} supports observation spaces {[s.__name__ for s in _SUPPORTED_OBSERVATION_SPACES]} "
                f"and Dict of them, got {observation_space}"
            )


def validate_arguments(arguments: dict[str, Any]) -> None:
    """Check the PeVFA arguments of an algorithm's constructor: a ValueError names the argument and what is valid."""
    representation, update_order = arguments["representation"], arguments["update_order"]
    if representation not in REPRESENTATIONS:
        raise ValueError(f"Unknown representation {representation!r}, valid choices: {REPRESENTATIONS}")
    if update_order not in UPDATE_ORDERS:
        raise ValueError(f"Unknown update_order {update_order!r}, valid choices: {UPDATE_ORDERS}")
    if arguments["history_targets"] not in HISTORY_TARGETS:
        raise ValueError(f"Unknown history_targets {arguments['history_targets']!r}, valid choices: {HISTORY_TARGETS}")
    if arguments["history_normalization"] not in HISTORY_NORMALIZATIONS:
        raise ValueError(
            f"Unknown history_normalization {arguments['history_normalization']!r}, valid choices: {HISTORY_NORMALIZATIONS}"
        )
    positive = {
        name: arguments[name]
        for name in ("embedding_dim", "history_buffer_size", "history_max_policies", "history_target_refresh")
    }
    positive["history_batch_size"] = arguments["history_batch_size"]
    non_negative = {
        name: arguments[name] for name in ("history_train_freq", "history_learning_starts", "n_state_action_pairs")
    }
    for name, value in positive.items():
        if not is_int(value) or value <= 0:
            raise ValueError(f"{name} must be a positive int, got {value!r}")
    for name, value in non_negative.items():
        if not is_int(value) or value < 0:
            raise ValueError(f"{name} must be an int >= 0, got {value!r}")
    k = arguments["history_batch_policies"]
    if k is not None and (not is_int(k) or k <= 0):
        raise ValueError(f"history_batch_policies must be None (uniform samples, the paper's) or a positive int, got {k!r}")
    _check_rollout_options(arguments)
    for name in ("fast_path", "flush_denormal", "bootstrap_truncated", "train_on_clipped_actions"):
        if not isinstance(arguments[name], (bool, np.bool_)):
            raise TypeError(f"{name} must be a bool, got {arguments[name]!r}")
    gradient = arguments["rollout_encoder_gradient"]
    if gradient is not None and not isinstance(gradient, (bool, np.bool_)):
        raise TypeError(f"rollout_encoder_gradient must be a bool or None, got {gradient!r}")
    lr = arguments["critic_learning_rate"]
    if lr is not None and not callable(lr) and (not isinstance(lr, (int, float)) or not np.isfinite(lr) or lr <= 0):
        raise ValueError(f"critic_learning_rate must be a positive finite float, a schedule or None, got {lr!r}")
    lam = arguments["value_target_lambda"]
    if lam is not None and (not isinstance(lam, (int, float)) or not 0.0 <= lam <= 1.0):
        raise ValueError(f"value_target_lambda must be in [0, 1] or None, got {lam!r}")


def _check_rollout_options(arguments: dict[str, Any]) -> None:
    """``rollout_episodes``, ``critic_minibatches``, and the options that shape the fast path's rollouts."""
    episodes = arguments["rollout_episodes"]
    if episodes is not None and (not isinstance(episodes, (int, np.integer)) or isinstance(episodes, bool) or episodes <= 0):
        raise ValueError(f"rollout_episodes must be None (rollouts of n_steps) or a positive int, got {episodes!r}")
    if arguments["critic_minibatches"] not in CRITIC_MINIBATCHES:
        raise ValueError(
            f"Unknown critic_minibatches {arguments['critic_minibatches']!r}, valid choices: {CRITIC_MINIBATCHES}"
        )
    if arguments["critic_minibatches"] == "even" and arguments["update_order"] != "critic_first":
        raise ValueError("critic_minibatches='even' shapes the critic's own epochs of update_order='critic_first'")
    rollout_options = {
        "rollout_episodes": episodes is not None,
        "bootstrap_truncated=False": arguments["bootstrap_truncated"] is False,
        "train_on_clipped_actions": arguments["train_on_clipped_actions"] is True,
    }
    needs_fast_path = [name for name, used in rollout_options.items() if used]
    if needs_fast_path and arguments["fast_path"] is False:
        raise ValueError(f"{needs_fast_path} shape the rollouts of the fast path: set fast_path=True")
