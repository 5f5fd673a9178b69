"""Recomputed history targets: lambda-returns of each policy under the current critic, aligned with its rollout."""

import gymnasium as gym
import numpy as np
import pytest
import torch as th
from conftest import FAST
from stable_baselines3.common.buffers import RolloutBuffer
from stable_baselines3.common.env_util import make_vec_env
from stable_baselines3.common.vec_env import VecNormalize

from sb3_pevfa import PolicyRecord, PPOPeVFA
from sb3_pevfa.pevfa import history as history_module
from sb3_pevfa.pevfa.history import PolicyHistory
from sb3_pevfa.pevfa.targets import lambda_returns

N_STEPS, N_ENVS, GAMMA, LAM = 6, 2, 0.9, 0.8


def _rollout(seed: int):
    """A rollout in SB3's buffer (rewards, values, episode starts) and its TD(lambda) returns as SB3 computes them."""
    rng = np.random.default_rng(seed)
    space = gym.spaces.Box(-1e6, 1e6, (1,))
    buffer = RolloutBuffer(N_STEPS, space, space, gamma=GAMMA, gae_lambda=LAM, n_envs=N_ENVS)
    values = rng.normal(size=(N_STEPS, N_ENVS)).astype(np.float32)
    starts = rng.random((N_STEPS, N_ENVS)) < 0.3
    for t in range(N_STEPS):
        obs = (1000 * seed + N_ENVS * t + np.arange(N_ENVS)).reshape(N_ENVS, 1)  # each observation names its sample
        buffer.add(obs, np.zeros((N_ENVS, 1)), rng.normal(size=N_ENVS), starts[t], th.as_tensor(values[t]), th.zeros(N_ENVS))
    last_values, last_dones = rng.normal(size=N_ENVS).astype(np.float32), rng.random(N_ENVS) < 0.5
    buffer.compute_returns_and_advantage(th.as_tensor(last_values), last_dones)
    last_obs = -(1000 * seed + np.arange(N_ENVS) + 1.0).reshape(N_ENVS, 1)
    return buffer, values, last_values, last_obs, last_dones


def test_lambda_returns_are_sb3s():
    buffer, values, last_values, _, last_dones = _rollout(0)
    returns = lambda_returns(buffer.rewards, values, buffer.episode_starts, last_values, last_dones, GAMMA, LAM)
    np.testing.assert_allclose(returns, buffer.returns, rtol=1e-6)
    # stacked rollouts: each its own recursion
    stacked = lambda_returns(*(np.stack([x, x]) for x in (buffer.rewards, values, buffer.episode_starts, last_values,
                             last_dones.astype(np.float32))), GAMMA, LAM)  # fmt: skip
    np.testing.assert_allclose(stacked[1], buffer.returns, rtol=1e-6)


@pytest.mark.parametrize("buffer_size", [100, 16])  # 16: the first policy's rollout is partly evicted
def test_recomputing_with_the_rollouts_own_values_gives_its_returns(tmp_path, buffer_size):
    """A value function that returns the values each rollout used reproduces SB3's returns, sample by sample (the
    alignment of rewards, episode starts and bootstrap), also for a rollout whose front was evicted, and after a
    save and load; a different value function moves every target."""
    space = gym.spaces.Box(-1e6, 1e6, (1,))
    history = PolicyHistory(space, space, n_params=2, n_state_action_pairs=0, buffer_size=buffer_size, transitions=True)
    lookup, expected = {}, {}
    for seed in (1, 2):
        buffer, values, last_values, last_obs, last_dones = _rollout(seed)
        empty = np.zeros((0, 1), np.float32)
        record = {"params": np.full(2, seed, np.float32), "states": empty, "actions": empty, "codes": np.zeros(0, np.float32)}
        policy_id = history.add_record(record)
        history.add_samples(buffer.observations, buffer.returns, policy_id, buffer.rewards, buffer.episode_starts,
                            last_obs, last_dones)  # fmt: skip
        lookup.update(zip(buffer.observations.reshape(-1).tolist(), values.reshape(-1).tolist()))
        lookup.update(zip(last_obs.reshape(-1).tolist(), last_values.tolist()))
        expected[policy_id] = buffer.returns.reshape(-1)

    def rollout_values(observations, policy_ids):
        return np.array([lookup[float(o)] for o in observations.reshape(-1)])

    _, before, ids = history.samples()
    assert history.recompute_targets(rollout_values, GAMMA, LAM) == len(before)
    _, after, _ = history.samples()
    for policy_id, returns in expected.items():
        kept = ids == policy_id
        np.testing.assert_allclose(after[kept], returns[-kept.sum() :], rtol=1e-5)
    history.save(tmp_path / "h")
    loaded = PolicyHistory(space, space, 2, 0, buffer_size=buffer_size, transitions=True).load(tmp_path / "h")
    assert loaded.recompute_targets(lambda o, i: rollout_values(o, i) + 1.0, GAMMA, LAM, exclude_policy=1) > 0
    _, moved, _ = loaded.samples()
    # (a step that ends its episode keeps its reward as target, whatever the values)
    assert not np.allclose(moved[ids != 1], after[ids != 1]) and np.array_equal(moved[ids == 1], after[ids == 1])
    with pytest.raises(ValueError, match="transitions"):
        PolicyHistory(space, space, 2, 0, transitions=False).load(tmp_path / "h")


@pytest.mark.parametrize("normalized", [False, True], ids=["plain", "vecnormalize"])
def test_the_model_recomputes_historical_targets_with_each_policys_chi(normalized, monkeypatch):
    """By hand for one historical policy; under VecNormalize in the statistics of the moment of recomputation (they
    are moved first): observations normalised anew, raw rewards through today's normalize_reward. The critic
    evaluates the history in chunks of 5 rows here, which must not reorder anything."""
    monkeypatch.setattr(history_module, "NORMALIZE_CHUNK", 5)
    env = VecNormalize(make_vec_env("Pendulum-v1", n_envs=1, seed=0)) if normalized else "Pendulum-v1"
    model = PPOPeVFA("MlpPolicy", env, history_targets="recomputed", **FAST)
    model.learn(256)
    history, policy = model.history, model.policy
    all_rows = history._samples.get(np.arange(history.n_samples))
    rewards = all_rows["rewards"]
    if normalized:
        assert (all_rows["raw_rewards"] <= 0).all() and (all_rows["raw_rewards"] > -16.3).all()  # Pendulum's raw
        # SB3 folded gamma * V(terminal observation) into the reward of the step its 200-step time limit cut: that
        # step alone has a bootstrap, and the rest of every reward is VecNormalize's own normalisation of the raw one
        assert np.flatnonzero(all_rows["raw_bootstraps"]).tolist() == [199]
        env.obs_rms.mean += 0.3
        env.ret_rms.var *= 4.0
        rewards = env.normalize_reward(all_rows["raw_rewards"]) + all_rows["raw_bootstraps"] / np.sqrt(
            env.ret_rms.var + env.epsilon
        )
    obs, frozen, ids = history.samples()
    assert model._refresh_history_targets() == int((ids != history.latest_policy_id).sum())
    _, targets, _ = history.samples()
    # by hand for one historical policy: its full rollout (64 steps, 1 env) under V(., chi of that policy)
    first = history.policy_ids[0]
    rows = ids == first
    last_obs = history._bootstraps[first]["obs"]
    last_obs = env.normalize_obs(last_obs) if normalized else last_obs
    policy.set_training_mode(False)
    with th.no_grad():
        chi = policy.embed(PolicyRecord.from_numpy(history.records([first])))
        values = policy.predict_values(th.as_tensor(obs[rows]), chi).numpy().reshape(64, 1)
        last = policy.predict_values(th.as_tensor(last_obs), chi).numpy().reshape(1)
    starts, last_starts = all_rows["episode_starts"][rows].reshape(64, 1), history._bootstraps[first]["last_episode_starts"]
    returns = lambda_returns(rewards[rows].reshape(64, 1), values, starts, last, last_starts, model.gamma, model.gae_lambda)
    np.testing.assert_allclose(targets[rows], returns.reshape(-1), rtol=1e-5, atol=1e-6)
    assert not np.allclose(targets[rows], frozen[rows])


def test_bad_history_target_settings():
    with pytest.raises(ValueError, match="valid choices"):
        PPOPeVFA("MlpPolicy", "Pendulum-v1", history_targets="monte_carlo")
    with pytest.raises(ValueError, match="history_target_refresh"):
        PPOPeVFA("MlpPolicy", "Pendulum-v1", history_targets="recomputed", history_target_refresh=0)


def test_an_unchanged_actor_gets_a_record_per_rollout_when_targets_are_recomputed():
    """The recorder records an unchanged policy once; recomputed targets need each rollout's own bootstrap, so there
    every rollout gets its record (here the actor never moves: its learning rate is 0)."""
    kwargs = dict(learning_rate=0.0, critic_learning_rate=1e-3, **FAST)
    frozen_actor = PPOPeVFA("MlpPolicy", "Pendulum-v1", **kwargs).learn(256)
    assert frozen_actor.history.n_policies == 1
    model = PPOPeVFA("MlpPolicy", "Pendulum-v1", history_targets="recomputed", **kwargs).learn(256)
    assert model.history.n_policies == 5 and model.history.n_samples == 256
    assert model._refresh_history_targets() == 256  # the latest record (the final policy) has no samples


def test_every_historical_policy_is_recomputed_with_its_own_chi_and_value_target_lambda():
    """Each historical policy's targets: its own chi, value_target_lambda (not gae_lambda), and the time limit's
    bootstrap in today's reward scale, by hand after the statistics moved."""
    env = VecNormalize(make_vec_env("Pendulum-v1", n_envs=1, seed=0))
    model = PPOPeVFA("MlpPolicy", env, history_targets="recomputed", gae_lambda=0.8, value_target_lambda=1.0, **FAST)
    model.learn(320)  # 5 rollouts of 64 steps: the 4th holds step 199, where the time limit cut the episode
    history, policy = model.history, model.policy
    all_rows = history._samples.get(np.arange(history.n_samples))
    assert all_rows["raw_bootstraps"][199] != 0
    env.obs_rms.mean += 0.3
    env.ret_rms.var *= 4.0
    rewards = env.normalize_reward(all_rows["raw_rewards"]) + all_rows["raw_bootstraps"] / np.sqrt(
        env.ret_rms.var + env.epsilon
    )
    obs, _, ids = history.samples()
    assert model._refresh_history_targets() == 320
    _, targets, _ = history.samples()
    policy.set_training_mode(False)
    for policy_id in history.policy_ids[:-1]:
        rows = ids == policy_id
        last_obs = env.normalize_obs(history._bootstraps[policy_id]["obs"])
        with th.no_grad():
            chi = policy.embed(PolicyRecord.from_numpy(history.records([policy_id])))
            values = policy.predict_values(th.as_tensor(obs[rows]), chi).numpy().reshape(64, 1)
            last = policy.predict_values(th.as_tensor(last_obs), chi).numpy().reshape(1)
        starts = all_rows["episode_starts"][rows].reshape(64, 1)
        last_starts = history._bootstraps[policy_id]["last_episode_starts"]
        returns = lambda_returns(rewards[rows].reshape(64, 1), values, starts, last, last_starts, model.gamma, 1.0)
        np.testing.assert_allclose(targets[rows], returns.reshape(-1), rtol=1e-5, atol=1e-5, err_msg=str(policy_id))


def test_refresh_keeps_the_latest_rollouts_targets_and_honours_its_period(monkeypatch):
    """Every history_target_refresh-th iteration (the 2nd, 4th, ...), the historical rollouts only: the rollout being
    trained on keeps its targets."""
    model = PPOPeVFA("MlpPolicy", "Pendulum-v1", history_targets="recomputed", history_target_refresh=2, **FAST)
    refresh, calls = model._refresh_history_targets, []

    def spy():
        history = model.history
        latest = history.latest_policy_id
        _, before, ids = history.samples()
        n = refresh()
        _, after, _ = history.samples()
        assert (ids == latest).sum() == 64  # the rollout being trained on
        np.testing.assert_array_equal(after[ids == latest], before[ids == latest])
        calls.append(n)
        return n

    monkeypatch.setattr(model, "_refresh_history_targets", spy)
    model.learn(320)
    assert calls == [0, 64, 0, 192, 0]  # iterations 2 and 4, the historical rollouts only
