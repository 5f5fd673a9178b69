"""The authors' time feature: the elapsed fraction of the episode, t / max_steps, appended to the observation."""

import numpy as np
from sb3_contrib.common.wrappers import TimeFeatureWrapper


class ElapsedTimeFeatureWrapper(TimeFeatureWrapper):
    """sb3-contrib's :class:`~sb3_contrib.common.wrappers.TimeFeatureWrapper` with the elapsed fraction
    ``t / max_steps`` (0 at reset; the authors' code) in place of its remaining fraction ``1 - t / max_steps``.
    In ``test_mode`` the feature stays 0."""

    def _get_obs(self, obs: np.ndarray | dict[str, np.ndarray]) -> np.ndarray | dict[str, np.ndarray]:
        obs = super()._get_obs(obs)
        assert self._max_steps is not None
        features = obs["observation"] if isinstance(obs, dict) else obs
        features[-1] = 0.0 if self._test_mode else self._current_step / self._max_steps
        return obs
