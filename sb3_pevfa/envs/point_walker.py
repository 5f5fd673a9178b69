"""The paper's 2-D Point Walker (App. B.1): a point moved by bounded displacements, rewarded by u = x^2 - y^2."""

from typing import ClassVar

import gymnasium as gym
import numpy as np
from gymnasium import spaces


def point_walker_observation(position: np.ndarray) -> np.ndarray:
    """(x, y, sin th, cos th, cos x, cos y) of positions ``(..., 2)``, th the polar angle."""
    x, y = position[..., 0], position[..., 1]
    theta = np.arctan2(y, x)
    return np.stack([x, y, np.sin(theta), np.cos(theta), np.cos(x), np.cos(y)], axis=-1).astype(np.float32)


def point_walker_utility(position: np.ndarray) -> np.ndarray:
    return position[..., 0] ** 2 - position[..., 1] ** 2


class PointWalkerEnv(gym.Env):
    """State (x, y, sin th, cos th, cos x, cos y); action a displacement in [-1, 1]^2, <x', y'> = <x, y> + a;
    reward (u' - u) / 10 with u = x^2 - y^2; episodes of ``horizon`` steps (paper: 10).

    The paper does not say where episodes start: here uniformly in [-start_range, start_range]^2.
    """

    metadata: ClassVar[dict] = {"render_modes": []}

    def __init__(self, horizon: int = 10, start_range: float = 1.0):
        if horizon <= 0 or start_range < 0:
            raise ValueError(f"horizon must be positive and start_range >= 0, got {horizon}, {start_range}")
        self.horizon = horizon
        self.start_range = start_range
        self.observation_space = spaces.Box(-np.inf, np.inf, (6,), np.float32)
        self.action_space = spaces.Box(-1.0, 1.0, (2,), np.float32)
        self.position = np.zeros(2)
        self.steps = 0

    def reset(self, *, seed: int | None = None, options: dict | None = None):
        super().reset(seed=seed)
        self.position = self.np_random.uniform(-self.start_range, self.start_range, size=2)
        self.steps = 0
        return point_walker_observation(self.position), {}

    def step(self, action):
        """Move by ``action`` (clipped to [-1, 1]^2); reward: the change of the utility, divided by 10."""
        action = np.clip(np.asarray(action, dtype=np.float64), -1.0, 1.0)
        utility = point_walker_utility(self.position)
        self.position = self.position + action
        self.steps += 1
        reward = float(point_walker_utility(self.position) - utility) / 10.0
        return point_walker_observation(self.position), reward, False, self.steps >= self.horizon, {}
