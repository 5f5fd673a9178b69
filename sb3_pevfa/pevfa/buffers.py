"""Rollout buffers whose value targets may use their own lambda (e.g. 1.0: Monte-Carlo style, as in the paper)."""

from typing import Any

import numpy as np
import torch as th
from stable_baselines3.common.buffers import DictRolloutBuffer, RolloutBuffer


class ValueTargetLambdaMixin:
    """Advantages use ``gae_lambda``; value targets (``returns``) use ``value_target_lambda`` when it is set.

    ``value_target_lambda=None`` gives SB3's TD(gae_lambda) returns unchanged; ``1.0`` gives discounted
    reward-to-go bootstrapped only at the end of the rollout (the paper's Monte-Carlo returns, up to that bootstrap).
    """

    gae_lambda: float
    advantages: np.ndarray

    def __init__(self, *args: Any, value_target_lambda: float | None = None, **kwargs: Any):
        if value_target_lambda is not None and not 0.0 <= value_target_lambda <= 1.0:
            raise ValueError(f"value_target_lambda must be in [0, 1] or None, got {value_target_lambda}")
        self.value_target_lambda = value_target_lambda
        super().__init__(*args, **kwargs)

    def compute_returns_and_advantage(self, last_values: th.Tensor, dones: np.ndarray) -> None:
        super().compute_returns_and_advantage(last_values, dones)  # type: ignore[misc]
        if self.value_target_lambda is None or self.value_target_lambda == self.gae_lambda:
            return
        advantages, gae_lambda = self.advantages.copy(), self.gae_lambda
        self.gae_lambda = self.value_target_lambda
        try:
            super().compute_returns_and_advantage(last_values, dones)  # type: ignore[misc]  # returns with the target lambda
        finally:
            self.gae_lambda, self.advantages = gae_lambda, advantages


class PeVFARolloutBuffer(ValueTargetLambdaMixin, RolloutBuffer):
    """:class:`~stable_baselines3.common.buffers.RolloutBuffer` with an optional separate value-target lambda."""


class PeVFADictRolloutBuffer(ValueTargetLambdaMixin, DictRolloutBuffer):
    """:class:`~stable_baselines3.common.buffers.DictRolloutBuffer` with an optional separate value-target lambda."""
