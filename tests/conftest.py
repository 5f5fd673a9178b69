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


#: PeVFA options under which a PeVFA algorithm is its SB3 base: no representation, no history, SB3's critic shape
AS_SB3 = dict(representation="none", history_train_freq=0, n_state_action_pairs=0)


def sb3_twin_runs(sb3_model, pevfa_model, timesteps: int) -> None:
    """Give the PeVFA model the SB3 model's weights, train both from the same global seeds, and check that they end
    with the same weights (SB3's ``value_net`` is the PeVFA head's ``output``)."""

    def renamed(key: str) -> str:
        return key.replace("value_net.", "value_net.output.", 1) if key.startswith("value_net.") else key

    weights = {renamed(k): v for k, v in sb3_model.policy.state_dict().items()}
    missing, unexpected = pevfa_model.policy.load_state_dict(weights, strict=False)
    assert not unexpected and all(k.startswith("behaviour") or k == "has_behaviour" for k in missing)
    for model in (sb3_model, pevfa_model):
        th.manual_seed(1)
        np.random.seed(1)
        model.learn(timesteps)
    assert pevfa_model._n_updates == sb3_model._n_updates
    for name, value in sb3_model.policy.state_dict().items():
        np.testing.assert_allclose(pevfa_model.policy.state_dict()[renamed(name)].numpy(), value.numpy(), atol=1e-5)
