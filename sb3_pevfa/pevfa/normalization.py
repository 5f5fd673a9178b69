"""The history under SB3's ``VecNormalize``: raw observations kept, everything handed out in today's statistics.

``VecNormalize`` rescales observations and rewards with running statistics that keep moving. A history sample
stored as the policy saw it would train the critic on inputs in an old coordinate system against targets in an old
reward scale. With a ``VecNormalize`` in the env's wrapper stack, the history instead keeps each sample's *raw*
observation (``VecNormalize.get_original_obs``) and the reward scale its target was computed in
(``sqrt(ret_rms.var + epsilon)``, 1 without ``norm_reward``), and every read re-expresses them:

- observations (and SPR's probe states) through ``VecNormalize.normalize_obs`` with today's statistics
  (``norm_obs``, ``norm_obs_keys``, ``clip_obs`` as the env applies them);
- value targets times ``scale_then / scale_now``;
- with recomputed targets (``history_targets="recomputed"``), rewards through ``normalize_reward`` (today's scale and
  ``clip_reward``) from the raw rewards, plus the time-limit bootstrap that SB3 folded into the reward, rescaled.

:class:`RolloutRecorder` collects the raw observations, rewards and scales of a rollout step by step.
"""

import warnings

import numpy as np
from gymnasium import spaces
from stable_baselines3.common.vec_env import VecCheckNan, VecEnv, VecEnvWrapper, VecMonitor, VecNormalize, VecVideoRecorder

from sb3_pevfa.pevfa.records import stack_observations

_warned: set[str] = set()


def reward_scale(env: VecNormalize) -> float:
    """The divisor of the rewards today: ``sqrt(ret_rms.var + epsilon)``, 1.0 without ``norm_reward``."""
    return float(np.sqrt(env.ret_rms.var + env.epsilon)) if env.norm_reward else 1.0


#: Wrappers that may sit outside the VecNormalize: they leave the observations as they are
_TRANSPARENT_WRAPPERS = (VecMonitor, VecCheckNan, VecVideoRecorder)


def find_vec_normalize(env: VecEnv | None, observation_space: spaces.Space) -> VecNormalize | None:
    """The ``VecNormalize`` of ``env`` whose statistics the history can re-express, or None.

    Only SB3's own class (a subclass may normalise otherwise), and only where every wrapper outside it leaves the
    observations alone (``VecTransposeImage`` or ``VecFrameStack`` on top change what its raw observations mean):
    otherwise a warning, once, and the history keeps what the policy saw."""
    outer = []
    while isinstance(env, VecEnvWrapper) and not isinstance(env, VecNormalize):
        outer.append(env)
        env = env.venv
    if not isinstance(env, VecNormalize):
        return None
    changing = [type(wrapper).__name__ for wrapper in outer if not isinstance(wrapper, _TRANSPARENT_WRAPPERS)]
    if changing or env.observation_space != observation_space:
        warn_once(
            "outer wrappers",
            f"{', '.join(changing) or 'A wrapper'} outside VecNormalize changes the observations: PeVFA cannot "
            "re-express them, so the history's observations, SPR probe states and value targets stay in the "
            "normalisation of their own rollout (stale once the statistics move); put VecNormalize outermost",
        )
        return None
    return env if renormalizable(env) else None


def renormalizable(env: VecNormalize) -> bool:
    """SB3's own ``VecNormalize`` (a subclass gets a warning, once)."""
    if type(env) is not VecNormalize:
        name = type(env).__name__
        warn_once(
            name,
            f"{name} is not SB3's VecNormalize: PeVFA cannot re-express its statistics, so the history's "
            "observations, SPR probe states and value targets stay in the normalisation of their own rollout "
            "(stale once the statistics move)",
        )
        return False
    return True


def warn_once(key: str, message: str) -> None:
    """A UserWarning, the first time ``key`` comes up in this process."""
    if key not in _warned:
        _warned.add(key)
        warnings.warn(message, stacklevel=4)


class RolloutRecorder:
    """Raw observations, raw rewards and reward scales of one rollout, one step at a time.

    :param env: The ``VecNormalize`` of the model's env
    :param first: The raw observation the first action is taken at (of the model's ``_last_obs``)
    """

    def __init__(self, env: VecNormalize, first: np.ndarray | dict):
        self.env = env
        self.observations = [first]
        self.rewards: list[np.ndarray] = []
        self.scales: list[np.ndarray] = []

    def step(self) -> None:
        """Called after each ``env.step``: the raw new observation, the raw reward and the scale it was divided by."""
        self.observations.append(self.env.get_original_obs())
        self.rewards.append(self.env.get_original_reward())  # float64, as VecNormalize divides them
        self.scales.append(np.full(self.env.num_envs, reward_scale(self.env)))

    def stacked(self) -> tuple[np.ndarray | dict, np.ndarray | dict, np.ndarray, np.ndarray]:
        """``(observations (n_steps, n_envs, ...), last observations, rewards (n_steps, n_envs), scales)``."""
        steps = stack_observations(self.observations[:-1])
        return steps, self.observations[-1], np.stack(self.rewards), np.stack(self.scales)
