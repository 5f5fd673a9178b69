import csv
import pathlib

import gymnasium as gym
import numpy as np
import pytest
import torch as th
from stable_baselines3.common.logger import configure

th.set_num_threads(1)

#: Tiny PeVFA budget: 64-step rollouts, historical updates from the start.
FAST = dict(n_steps=64, batch_size=32, n_epochs=2, history_learning_starts=0, history_train_freq=16, seed=0)


class DictPendulum(gym.ObservationWrapper):
    """Pendulum with a Dict observation of two vector keys."""

    def __init__(self):
        super().__init__(gym.make("Pendulum-v1"))
        self.observation_space = gym.spaces.Dict(
            {"angle": gym.spaces.Box(-1, 1, (2,), np.float32), "speed": gym.spaces.Box(-8, 8, (1,), np.float32)}
        )

    def observation(self, observation):
        return {"angle": observation[:2], "speed": observation[2:]}


def read_progress(folder: pathlib.Path) -> list[dict[str, str]]:
    with open(folder / "progress.csv") as handle:
        return list(csv.DictReader(handle))


@pytest.fixture
def csv_logger(tmp_path):
    return configure(str(tmp_path / "logs"), ["csv"]), tmp_path / "logs"


def actor_parameters(policy) -> th.Tensor:
    return policy.layout.flatten(policy)


def module_parameters(module) -> th.Tensor:
    return th.cat([p.detach().flatten().clone() for p in module.parameters()])
