"""The fast path (sb3_pevfa.pevfa.fast_path) computes what SB3's own rollout and PPO update compute."""

import gymnasium as gym
import numpy as np
import pytest
import torch as th
from conftest import DictPendulum, module_parameters
from stable_baselines3.common.callbacks import BaseCallback
from stable_baselines3.common.env_util import make_vec_env

from sb3_pevfa import PPOPeVFA
from sb3_pevfa.pevfa.fast_path import predict_values

FIELDS = ("observations", "actions", "log_probs", "rewards", "episode_starts", "values", "returns", "advantages")


class RolloutRecorder(BaseCallback):
    """Copies of the rollout buffer at the end of every rollout (values, returns and advantages computed)."""

    def __init__(self):
        super().__init__()
        self.rollouts: list[dict[str, np.ndarray]] = []

    def _on_step(self) -> bool:
        return True

    def _on_rollout_end(self) -> None:
        buffer = self.model.rollout_buffer
        if isinstance(buffer.observations, dict):
            copy = {f"obs_{k}": v.copy() for k, v in buffer.observations.items()}
            copy.update({name: getattr(buffer, name).copy() for name in FIELDS[1:]})
        else:
            copy = {name: getattr(buffer, name).copy() for name in FIELDS}
        self.rollouts.append(copy)


def _run(env_id, fast_path: bool, **kwargs):
    env = make_vec_env(DictPendulum if env_id == "DictPendulum" else env_id, n_envs=2, seed=0)
    options = dict(n_steps=128, batch_size=64, n_epochs=2, history_learning_starts=0, history_train_freq=32, seed=0)
    policy = "MultiInputPolicy" if env_id == "DictPendulum" else "MlpPolicy"
    model = PPOPeVFA(policy, env, fast_path=fast_path, **options, **kwargs)
    recorder = RolloutRecorder()
    model.learn(3 * 128 * 2, callback=recorder)
    return model, recorder.rollouts


@pytest.mark.parametrize(
    "env_id, kwargs",
    [
        ("Pendulum-v1", {}),  # Gaussian; episodes of 200 steps are truncated inside the rollouts (bootstrap)
        ("CartPole-v1", dict(representation="spr")),  # Categorical, terminations
        ("DictPendulum", dict(representation="none")),
        ("Pendulum-v1", dict(use_sde=True, update_order="critic_first", clip_range_vf=0.2, target_kl=0.02)),
        ("Pendulum-v1", dict(use_sde=True, sde_sample_freq=4)),  # the noise drawn again every 4 steps
        ("Pendulum-v1", dict(value_target_lambda=1.0, representation_objectives=("cl",))),
    ],
)
def test_fast_path_matches_sb3(env_id, kwargs):
    fast_model, fast = _run(env_id, True, **kwargs)
    slow_model, slow = _run(env_id, False, **kwargs)
    assert len(fast) == len(slow) == 3
    if env_id.endswith("Pendulum-v1"):  # a truncated episode ended inside the second rollout: bootstrap compared
        assert slow[1]["episode_starts"][1:].any()
    for i, (a, b) in enumerate(zip(fast, slow)):
        assert a.keys() == b.keys()
        for name in a:
            # round-off of batched vs per-step critic calls grows a little with every update
            assert np.allclose(a[name], b[name], rtol=1e-4, atol=1e-4 * (i + 1)), (i, name, np.abs(a[name] - b[name]).max())
    assert th.allclose(module_parameters(fast_model.policy), module_parameters(slow_model.policy), atol=1e-4)
    assert fast_model._n_updates == slow_model._n_updates


def test_values_in_chunks_equal_one_pass(monkeypatch):
    model = PPOPeVFA("MlpPolicy", "Pendulum-v1", n_steps=64, batch_size=32, seed=0)
    monkeypatch.setattr("sb3_pevfa.pevfa.fast_path.VALUE_CHUNK", 7)  # 20 observations: chunks of 7, 7 and 6
    obs = th.as_tensor(np.random.default_rng(0).uniform(-1, 1, (20, 3)), dtype=th.float32)
    chi = th.randn(20, model.policy.representation.embedding_dim)
    with th.no_grad():
        chunked, whole = predict_values(model.policy, obs, chi), model.policy.predict_values(obs, chi).flatten()
        assert chunked.shape == (20,) and th.allclose(chunked, whole, atol=1e-6)
        assert th.allclose(predict_values(model.policy, obs), model.policy.predict_values(obs).flatten(), atol=1e-6)


def test_early_stopping_and_logs_match(tmp_path):
    from stable_baselines3.common.logger import configure

    logs = {}
    for fast_path in (True, False):
        model = PPOPeVFA("MlpPolicy", "Pendulum-v1", n_steps=256, batch_size=64, n_epochs=10, target_kl=0.001, seed=1,
                         history_learning_starts=0, fast_path=fast_path)  # fmt: skip
        model.set_logger(configure(str(tmp_path / str(fast_path)), ["csv"]))
        model.learn(512)
        logs[fast_path] = dict(model.logger.name_to_value)
        logs[fast_path]["n_updates"] = model._n_updates
    assert logs[True]["n_updates"] == logs[False]["n_updates"] < 20  # early stopping happened at the same epoch
    for key in ("train/approx_kl", "train/clip_fraction", "train/value_loss", "train/policy_gradient_loss", "train/std"):
        assert np.isclose(logs[True][key], logs[False][key], rtol=1e-3, atol=1e-6), key


def test_per_step_callbacks_see_sb3_locals():
    seen = set()

    class Probe(BaseCallback):
        def _on_step(self) -> bool:
            seen.update(self.locals)
            return True

    env = gym.make("Pendulum-v1")
    PPOPeVFA("MlpPolicy", env, n_steps=64, batch_size=32, n_epochs=1, seed=0).learn(64, callback=Probe())
    assert {"actions", "clipped_actions", "new_obs", "rewards", "dones", "infos", "obs_tensor"} <= seen
    # values and log-probabilities come from batched passes after the rollout (fast_path=False has them per step)
    assert not {"values", "log_probs"} & seen
