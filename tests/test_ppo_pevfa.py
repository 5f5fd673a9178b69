import copy
import warnings

import gymnasium as gym
import numpy as np
import pytest
import torch as th
from conftest import (
    AS_SB3,
    FAST,
    DictPendulum,
    actor_parameters,
    module_parameters,
    needs_denormal_flush,
    read_progress,
    sb3_twin_runs,
)
from stable_baselines3 import A2C, PPO
from stable_baselines3.common.buffers import RolloutBuffer
from stable_baselines3.common.callbacks import CheckpointCallback
from stable_baselines3.common.env_util import make_vec_env
from stable_baselines3.common.envs import FakeImageEnv
from stable_baselines3.common.policies import ActorCriticPolicy
from stable_baselines3.common.vec_env import DummyVecEnv, VecFrameStack, VecNormalize

from sb3_pevfa import PAPER_SCHEDULE, REPRESENTATIONS, PolicyHistory, PolicyHistoryCallback, PolicyRecord, PPOPeVFA
from sb3_pevfa.pevfa import normalization
from sb3_pevfa.pevfa.buffers import PeVFARolloutBuffer
from sb3_pevfa.pevfa.denormals import denormals_flushed, flush_denormals
from sb3_pevfa.pevfa.fast_path import flat_observations
from sb3_pevfa.pevfa.records import ActorLayout
from sb3_pevfa.ppo_pevfa.policies import PeVFAActorCriticPolicy


@pytest.mark.parametrize("env_id", ["CartPole-v1", "Pendulum-v1"])
@pytest.mark.parametrize("representation", REPRESENTATIONS)
def test_every_representation_runs(env_id, representation, csv_logger):
    model = PPOPeVFA("MlpPolicy", env_id, representation=representation, **FAST)
    model.set_logger(csv_logger[0])
    model.learn(256)
    # one record per update (4 rollouts) plus the final policy
    assert model.history.n_policies == 5 and model.history.n_samples == 256
    # SB3 writes the logs of an update at the next iteration: rows 1-3 hold updates 1-3
    rows = read_progress(csv_logger[1])
    assert len(rows) == 4
    last = rows[-1]
    assert int(last["pevfa/n_policies"]) == 3 and int(last["pevfa/history_samples"]) == 192
    assert int(last["pevfa/history_updates"]) == 4 and float(last["pevfa/history_value_loss"]) >= 0
    assert "train/value_loss" in last and "train/policy_gradient_loss" in last
    if representation != "none":
        assert float(last["pevfa/embedding_norm"]) > 0
    # the first update has no historical policy to train on
    assert int(rows[1]["pevfa/history_updates"]) == 0


@pytest.mark.parametrize("representation", ["opr", "spr"])
def test_dict_observations(representation):
    model = PPOPeVFA("MultiInputPolicy", DictPendulum(), representation=representation, **FAST)
    model.learn(192)
    obs, _, _ = model.history.sample(8)
    assert set(obs) == {"angle", "speed"}
    # Dict keys flattened into one state of 3; OPR records no pairs (nothing reads them)
    assert model.history.records([0])["states"].shape == (1, 200 if representation == "spr" else 0, 3)


@pytest.mark.parametrize("representation", ["opr", "spr"])
def test_vectorized_and_normalized_envs(representation):
    """Under VecNormalize the history keeps the raw observations (Pendulum's (cos, sin) on the unit circle) and the
    reward scale of each target, and hands them out in today's statistics: exactly what the env gives now."""
    env = VecNormalize(make_vec_env("Pendulum-v1", n_envs=4, seed=0))
    model = PPOPeVFA("MlpPolicy", env, representation=representation, **{**FAST, "n_steps": 32})
    model.learn(384)
    history, buffer = model.history, model.rollout_buffer
    assert history.renormalize and history.n_samples == 384 and history.n_policies == 4
    raw_obs, raw_targets, ids = history.samples(raw=True)
    np.testing.assert_allclose(np.hypot(raw_obs[:, 0], raw_obs[:, 1]), 1.0, rtol=1e-5)  # Pendulum's raw (cos, sin)
    # a rollout with frozen statistics: its samples read back as the rollout buffer holds them (step-major there,
    # env-major in the buffer after PPO's update), the targets as the rollout's returns
    env.training = False
    model.learn(128, reset_num_timesteps=False)
    obs, targets, ids = history.samples()
    np.testing.assert_array_equal(obs[-128:], buffer.observations.reshape(4, 32, 3).swapaxes(0, 1).reshape(-1, 3))
    np.testing.assert_array_equal(targets[-128:], buffer.returns.reshape(4, 32).T.reshape(-1))
    assert set(ids[-128:]) == {history.policy_ids[-2]}  # the policy that collected them (the last is the final)
    # statistics moved since: every read is in the new ones
    raw_obs, raw_targets, _ = history.samples(raw=True)
    scales = history._samples.get(np.arange(history.n_samples))["reward_scales"]
    env.obs_rms.mean += 0.5
    env.obs_rms.var *= 2.0
    env.ret_rms.var *= 4.0
    obs, targets, _ = history.samples()
    np.testing.assert_array_equal(obs, env.normalize_obs(raw_obs))
    np.testing.assert_allclose(targets, raw_targets * scales / np.sqrt(env.ret_rms.var + env.epsilon), rtol=1e-6)
    batch_obs, batch_targets, batch_ids = history.sample_grouped(64, 4)
    table = {(row.tobytes(), target, pid) for row, target, pid in zip(obs, targets, history.samples()[2])}
    assert all((row.tobytes(), t, pid) in table for row, t, pid in zip(batch_obs, batch_targets, batch_ids))  # whole rows
    if representation == "spr":  # the probe states of every record: raw, read in today's statistics
        raw_states = history.records(history.policy_ids, raw=True)["states"]
        np.testing.assert_allclose(np.hypot(raw_states[..., 0], raw_states[..., 1]), 1.0, rtol=1e-5)
        states = history.records(history.policy_ids)["states"]
        np.testing.assert_array_equal(states, env.normalize_obs(raw_states.reshape(-1, 3)).reshape(states.shape))


@needs_denormal_flush
def test_flush_denormals_restores_the_threads_setting():
    denormal = th.tensor([1e-40])
    assert not denormals_flushed() and (denormal * 1.0).item() > 0
    with flush_denormals():
        assert denormals_flushed() and (denormal * 1.0).item() == 0.0
    assert not denormals_flushed()
    with flush_denormals(False):
        assert not denormals_flushed()
    with pytest.raises(RuntimeError), flush_denormals():  # restored on an exception too
        raise RuntimeError
    assert not denormals_flushed()
    threads = th.get_num_threads()
    th.set_num_threads(2)  # torch's worker threads keep their own setting: nothing is flushed
    try:
        with flush_denormals():
            assert not denormals_flushed()
    finally:
        th.set_num_threads(threads)
    th.set_flush_denormal(True)
    try:
        with flush_denormals():  # a user's own setting stays on after the update
            assert denormals_flushed()
        assert denormals_flushed()
    finally:
        th.set_flush_denormal(False)


@needs_denormal_flush
def test_flush_denormal_clears_denormal_adam_moments_in_the_update_only(tmp_path):
    """Denormal moments (of units without gradient) become 0 in the update; the rollout runs with IEEE arithmetic;
    ``flush_denormal=False`` keeps them, and survives save / load."""
    seen = []
    for flush in (True, False):
        model = PPOPeVFA("MlpPolicy", "Pendulum-v1", flush_denormal=flush, **FAST)
        model.learn(64)
        hidden, output = model.policy.value_net.hidden[0], model.policy.value_net.output
        with th.no_grad():  # a dead ReLU unit: no gradient reaches its weights; their moments decay by 0.9 a step
            hidden.weight[0], hidden.bias[0] = 0.0, -1.0
        state = model.policy.optimizer.state[output.weight]
        state["exp_avg"][0, 0] = 1e-40
        rollout = model.collect_rollouts
        model.collect_rollouts = lambda *a, rollout=rollout, **k: seen.append(denormals_flushed()) or rollout(*a, **k)  # type: ignore
        model.learn(64, reset_num_timesteps=False)
        moment = state["exp_avg"][0, 0].item()
        assert moment == 0.0 if flush else 0.0 < moment < th.finfo(th.float32).tiny
        assert not denormals_flushed()
    assert seen == [False, False]
    model.save(tmp_path / "model.zip")
    assert PPOPeVFA.load(tmp_path / "model.zip").flush_denormal is False


def test_history_normalization_rollout_keeps_what_the_rollout_saw(tmp_path):
    """``history_normalization="rollout"`` (the ablation of the behaviour before 0.1.0): under VecNormalize the
    history keeps the normalised observations and targets of each rollout, which moved statistics leave as they were."""
    env = VecNormalize(make_vec_env("Pendulum-v1", n_envs=2, seed=0))
    model = PPOPeVFA("MlpPolicy", env, history_normalization="rollout", **{**FAST, "n_steps": 32}).learn(128)
    history, buffer = model.history, model.rollout_buffer
    assert not history.renormalize and history.normalizer is None
    obs, targets, _ = history.samples()
    seen = buffer.observations.reshape(2, 32, 3).swapaxes(0, 1).reshape(-1, 3)  # env-major after PPO
    np.testing.assert_array_equal(obs[-64:], seen)
    np.testing.assert_array_equal(targets[-64:], buffer.returns.reshape(2, 32).T.reshape(-1))
    env.obs_rms.mean += 0.5
    env.ret_rms.var *= 4.0
    for got, want in zip(history.samples(), (obs, targets)):
        np.testing.assert_array_equal(got, want)
    model.set_env(env)  # the same mode: the history stays
    assert model.history is history and history.normalizer is None
    # saved and loaded, the option and its history come back together
    model.save(tmp_path / "model")
    model.save_history(tmp_path / "history")
    loaded = PPOPeVFA.load(tmp_path / "model", env=env)
    assert loaded.history_normalization == "rollout"
    loaded.load_history(tmp_path / "history")
    for got, want in zip(loaded.history.samples(), (obs, targets)):
        np.testing.assert_array_equal(got, want)
    current = PPOPeVFA.load(tmp_path / "model", env=env, history_normalization="current")
    with pytest.raises(ValueError, match=r"renormalize: file has False.*history_normalization='rollout'"):
        current.load_history(tmp_path / "history")
    with pytest.raises(ValueError, match=r"history_normalization 'today', valid choices: \('current', 'rollout'\)"):
        PPOPeVFA("MlpPolicy", env, history_normalization="today")


def test_the_first_raw_observation_of_a_run_under_vec_normalize():
    """The raw observation that the first action of a run (after learn's env reset) is taken at is the one the
    history keeps: with frozen, non-trivial statistics, the history's first rollout reads back as the buffer."""
    env = VecNormalize(make_vec_env("Pendulum-v1", n_envs=2, seed=0))
    env.obs_rms.mean[:] = [0.3, -0.2, 1.0]
    env.obs_rms.var[:] = [0.5, 2.0, 4.0]
    env.training = False
    model = PPOPeVFA("MlpPolicy", env, **{**FAST, "n_steps": 32}).learn(64)
    obs, _, ids = model.history.samples()
    assert set(ids) == {model.history.policy_ids[0]}  # the first policy's rollout, from learn's reset
    seen = model.rollout_buffer.observations.reshape(2, 32, 3).swapaxes(0, 1).reshape(-1, 3)  # env-major after PPO
    np.testing.assert_array_equal(obs, seen)


@pytest.mark.parametrize("representation", ["opr", "spr"])
def test_dict_observations_under_vec_normalize_with_some_keys(representation, monkeypatch):
    """``norm_obs_keys``: the normalised key reads in today's statistics, the other stays raw; so do SPR's flattened
    Dict probe states (``angle`` then ``speed``), with nothing announced as stale."""
    env = VecNormalize(make_vec_env(DictPendulum, n_envs=2, seed=0), norm_obs_keys=["speed"])
    monkeypatch.setattr(normalization, "_warned", set())  # announced once per process: as if this were the first
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        model = PPOPeVFA("MultiInputPolicy", env, representation=representation, **FAST).learn(192)
    assert not [w for w in caught if "normalisation of their record" in str(w.message)]
    history = model.history
    raw, _, _ = history.samples(raw=True)
    np.testing.assert_allclose(np.hypot(raw["angle"][:, 0], raw["angle"][:, 1]), 1.0, rtol=1e-5)
    assert np.abs(raw["speed"]).max() <= 8.0
    env.obs_rms["speed"].mean += 1.0
    env.obs_rms["speed"].var *= 3.0
    obs, _, _ = history.samples()
    np.testing.assert_array_equal(obs["angle"], raw["angle"])
    np.testing.assert_array_equal(obs["speed"], env.normalize_obs(raw)["speed"])
    assert history.raw_states
    if representation == "spr":  # raw probe states: a raw angle on the unit circle, a raw speed within +-8
        raw_states = history.records(history.policy_ids, raw=True)["states"]
        np.testing.assert_allclose(np.hypot(raw_states[..., 0], raw_states[..., 1]), 1.0, rtol=1e-5)
        assert np.abs(raw_states[..., 2]).max() <= 8.0 and np.abs(raw_states[..., 2]).max() > 1.0
        states = history.records(history.policy_ids)["states"]
        speed = env.normalize_obs({"angle": raw_states[..., :2], "speed": raw_states[..., 2:]})["speed"]
        np.testing.assert_array_equal(states[..., :2], raw_states[..., :2])
        np.testing.assert_allclose(states[..., 2:], speed, rtol=1e-6)
        chi = model.policy.embed(PolicyRecord.from_numpy(history.records(history.policy_ids)))
        env.obs_rms["speed"].mean -= 1.0  # the encoder reads the states of today's statistics
        assert not th.allclose(chi, model.policy.embed(PolicyRecord.from_numpy(history.records(history.policy_ids))))


def test_dict_probe_states_with_a_normalised_image_key():
    """VecNormalize turns every key it normalises into a float Box (no longer an image): that key's part of the
    flattened probe state is raw too, and reads in today's statistics; the unnormalised key stays as recorded."""
    from stable_baselines3.common.envs import SimpleMultiObsEnv

    np.random.seed(0)  # SimpleMultiObsEnv draws its observations from the global RNG when it is built
    env = VecNormalize(make_vec_env(lambda: SimpleMultiObsEnv(random_start=False), n_envs=1), norm_obs_keys=["img"])
    model = PPOPeVFA("MultiInputPolicy", env, representation="spr", n_state_action_pairs=8, **FAST).learn(128)
    history, pixels = model.history, int(np.prod(env.observation_space["img"].shape))
    env.obs_rms["img"].mean += 0.25
    raw = history.records(history.policy_ids, raw=True)["states"]
    states = history.records(history.policy_ids)["states"]
    image = env.normalize_obs({"img": raw[..., :pixels].reshape(-1, *env.observation_space["img"].shape)})["img"]
    np.testing.assert_allclose(states[..., :pixels], image.reshape(raw[..., :pixels].shape), rtol=1e-6)
    np.testing.assert_array_equal(states[..., pixels:], raw[..., pixels:])
    assert not np.allclose(states[..., :pixels], raw[..., :pixels])


def test_wrappers_that_leave_observations_alone_may_sit_outside_vec_normalize(monkeypatch):
    from stable_baselines3.common.vec_env import VecCheckNan, VecMonitor

    monkeypatch.setattr(normalization, "_warned", set())
    env = VecCheckNan(VecMonitor(VecNormalize(DummyVecEnv([lambda: gym.make("Pendulum-v1")] * 2))))
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # nothing to announce
        model = PPOPeVFA("MlpPolicy", env, **FAST)
    assert model.history.renormalize and model.history.normalizer is env.venv.venv


def test_wrappers_that_change_observations_outside_vec_normalize_keep_the_old_behaviour(monkeypatch):
    """Raw observations below a VecFrameStack (or SB3's own VecTransposeImage) are not what the policy reads: the
    history keeps what the policy saw, and says so once."""
    monkeypatch.setattr(normalization, "_warned", set())
    stacked = VecFrameStack(VecNormalize(make_vec_env("Pendulum-v1", n_envs=2, seed=0)), n_stack=2)
    with pytest.warns(UserWarning, match="VecFrameStack outside VecNormalize changes the observations"):
        model = PPOPeVFA("MlpPolicy", stacked, **FAST)
    assert not model.history.renormalize
    model.learn(128)
    seen = model.rollout_buffer.observations.reshape(2, 64, 6).swapaxes(0, 1).reshape(-1, 6)  # env-major after PPO
    np.testing.assert_array_equal(model.history.samples()[0][-128:], seen)  # the stacked, normalised frames
    image_env = make_vec_env(lambda: FakeImageEnv(screen_height=36, screen_width=36, n_channels=1), n_envs=1)
    images = VecNormalize(image_env, norm_obs=False)
    model = PPOPeVFA("CnnPolicy", images, **{**FAST, "n_steps": 32, "batch_size": 16})
    assert not model.history.renormalize  # SB3 put a VecTransposeImage outside it
    model.learn(64)


def test_the_reward_scale_is_one_without_norm_reward():
    env = VecNormalize(make_vec_env("Pendulum-v1", n_envs=1), norm_reward=False)
    env.ret_rms.var[...] = 4.0
    assert normalization.reward_scale(env) == 1.0
    env.norm_reward = True
    assert normalization.reward_scale(env) == pytest.approx(np.sqrt(4.0 + env.epsilon))


def test_a_vec_normalize_of_another_observation_space_is_not_used(monkeypatch):
    monkeypatch.setattr(normalization, "_warned", set())
    env = VecNormalize(make_vec_env("Pendulum-v1", n_envs=1))
    with pytest.warns(UserWarning, match="A wrapper outside VecNormalize changes the observations"):
        assert normalization.find_vec_normalize(env, gym.spaces.Box(-1, 1, (4,), np.float32)) is None
    assert normalization.find_vec_normalize(env, env.observation_space) is env


def test_a_history_under_a_loaded_vec_normalize(tmp_path):
    env = VecNormalize(make_vec_env("Pendulum-v1", n_envs=2, seed=0))
    model = PPOPeVFA("MlpPolicy", env, **FAST).learn(256)
    model.save(tmp_path / "model")
    model.save_history(tmp_path / "history")
    env.save(tmp_path / "statistics.pkl")
    expected = model.history.samples()
    loaded_env = VecNormalize.load(tmp_path / "statistics.pkl", make_vec_env("Pendulum-v1", n_envs=2, seed=1))
    loaded = PPOPeVFA.load(tmp_path / "model", env=loaded_env)
    loaded.load_history(tmp_path / "history")
    assert loaded.history.renormalize and loaded.history.normalizer is loaded_env
    for got, want in zip(loaded.history.samples(), expected):
        np.testing.assert_array_equal(got, want)
    loaded.learn(64, reset_num_timesteps=False)
    assert loaded.history.n_policies == model.history.n_policies + 1
    # raw observations do not go to a model without VecNormalize, nor to its env
    plain = PPOPeVFA.load(tmp_path / "model", env=make_vec_env("Pendulum-v1", n_envs=2))
    hint = r"renormalize: file has True.*with env=VecNormalize.* and history_normalization='current'"
    with pytest.raises(ValueError, match=hint):
        plain.load_history(tmp_path / "history")
    with pytest.raises(ValueError, match="recorded with a VecNormalize"):
        loaded.set_env(make_vec_env("Pendulum-v1", n_envs=2))
    assert loaded.env is loaded_env  # the refused env did not replace it


def test_a_history_of_transitions_under_vec_normalize_loads_every_stored_field(tmp_path):
    """Recomputed targets under VecNormalize keep raw rewards and time-limit bootstraps per sample and each rollout's
    bootstrap: a saved and loaded history holds every one of them as it was."""
    env = VecNormalize(make_vec_env("Pendulum-v1", n_envs=2, seed=0))
    model = PPOPeVFA("MlpPolicy", env, history_targets="recomputed", **FAST).learn(192)
    history = model.history
    model.save_history(tmp_path / "history")
    loaded = PPOPeVFA("MlpPolicy", env, history_targets="recomputed", **FAST)
    with pytest.warns(UserWarning, match="not the history of this model's moment"):  # a fresh model: at step 0
        loaded.load_history(tmp_path / "history")
    rows = np.arange(history.n_samples)
    want, got = history._samples.get(rows), loaded.history._samples.get(rows)
    assert set(got) == set(want) >= {"raw_rewards", "raw_bootstraps", "reward_scales"}
    for name in want:
        np.testing.assert_array_equal(got[name], want[name], err_msg=name)
    assert list(loaded.history._bootstraps) == list(history._bootstraps) == history.policy_ids[:-1]
    for policy_id, bootstrap in history._bootstraps.items():
        for name, array in bootstrap.items():
            np.testing.assert_array_equal(loaded.history._bootstraps[policy_id][name], array, err_msg=name)


def test_a_vec_normalize_it_cannot_re_express_is_announced_once(monkeypatch):
    class MyNormalize(VecNormalize):
        pass

    monkeypatch.setattr(normalization, "_warned", set())
    with pytest.warns(UserWarning, match="MyNormalize is not SB3's VecNormalize: .* stay in the normalisation"):
        model = PPOPeVFA("MlpPolicy", MyNormalize(make_vec_env("Pendulum-v1", n_envs=2, seed=0)), **FAST)
    assert not model.history.renormalize and model.history.normalizer is None
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        PPOPeVFA("MlpPolicy", MyNormalize(make_vec_env("Pendulum-v1", n_envs=2, seed=0)), **FAST).learn(64)


def _predictions(model, obs):
    actions, _ = model.predict(obs, deterministic=True)
    model.policy.set_training_mode(False)
    with th.no_grad():
        values = model.policy.predict_values(model.policy.obs_to_tensor(obs)[0])
    return actions, values.numpy()


@pytest.mark.parametrize("representation", REPRESENTATIONS)
def test_save_load_roundtrip(tmp_path, representation):
    model = PPOPeVFA(
        "MlpPolicy",
        "Pendulum-v1",
        representation=representation,
        critic_learning_rate=2e-3,
        update_order="critic_first",
        value_target_lambda=1.0,
        history_buffer_size=150,
        history_max_policies=3,
        policy_kwargs=dict(critic_head_arch=[32]),
        **FAST,
    )
    model.learn(256)
    obs = np.stack([model.observation_space.sample() for _ in range(10)])
    expected = _predictions(model, obs)
    model.save(tmp_path / "model")
    model.save_history(tmp_path / "history")
    loaded = PPOPeVFA.load(tmp_path / "model", env=None)
    for name in ("critic_learning_rate", "update_order", "value_target_lambda", "history_buffer_size", "history_max_policies"):
        assert getattr(loaded, name) == getattr(model, name)
    assert loaded.policy.representation_name == representation and loaded.policy.critic_head_arch == [32]
    for got, want in zip(_predictions(loaded, obs), expected):
        np.testing.assert_array_equal(got, want)
    # optimizer state (both parameter groups) round-trips
    assert [g["name"] for g in loaded.policy.optimizer.param_groups] == ["actor", "critic"]
    assert [g["lr"] for g in loaded.policy.optimizer.param_groups] == [g["lr"] for g in model.policy.optimizer.param_groups]
    saved, restored = (m.policy.optimizer.state_dict()["state"] for m in (model, loaded))
    assert saved.keys() == restored.keys() and len(saved) > 0
    for key, state in saved.items():
        assert all(th.equal(state[name], restored[key][name]) for name in ("step", "exp_avg", "exp_avg_sq"))
    assert loaded.history.n_policies == 0
    loaded.load_history(tmp_path / "history")
    assert loaded.history.policy_ids == model.history.policy_ids and loaded.history.n_samples == 128  # 2 policies x 64
    for got, want in zip(loaded.history.samples(), model.history.samples()):
        np.testing.assert_array_equal(got, want)


def test_load_history_of_another_model_is_refused(tmp_path):
    opr = PPOPeVFA("MlpPolicy", "Pendulum-v1", representation="opr", **FAST)
    opr.learn(64)
    opr.save_history(tmp_path / "opr")
    spr = PPOPeVFA("MlpPolicy", "Pendulum-v1", representation="spr", **FAST)
    with pytest.raises(ValueError, match="representation"):
        spr.load_history(tmp_path / "opr")
    cartpole = PPOPeVFA("MlpPolicy", "CartPole-v1", representation="opr", **FAST)
    with pytest.raises(ValueError, match="observation_shapes"):
        cartpole.load_history(tmp_path / "opr")


def _final_state(model):
    return th.cat([p.detach().flatten() for p in model.policy.parameters()]).numpy()


@pytest.mark.parametrize("representation", ["opr", "spr"])
def test_same_seed_same_run(representation):
    def run(seed):
        model = PPOPeVFA("MlpPolicy", "Pendulum-v1", representation=representation, **{**FAST, "seed": seed})
        return _final_state(model.learn(256))

    np.testing.assert_array_equal(run(0), run(0))
    assert not np.array_equal(run(0), run(1))


@pytest.mark.parametrize("update_order", ["joint", "critic_first"])
def test_resume_with_history_equals_uninterrupted_run(tmp_path, update_order):
    """Model + history saved, RNG states restored: learning on continues bit for bit as without the interruption.

    SB3's load resets the environment (seeded with the model's seed), so the reference run does the same. The
    environments are created seeded: created with ``seed=None`` the two runs are not bit-identical (measured: up to
    6e-8 joint, 2e-4 critic-first)."""

    def make_env():
        return make_vec_env("Pendulum-v1", n_envs=1, seed=0)

    kwargs = dict(representation="spr", update_order=update_order, **FAST)
    reference = PPOPeVFA("MlpPolicy", make_env(), **kwargs)
    reference.learn(192)
    reference.save(tmp_path / "model")
    reference.save_history(tmp_path / "history")
    reference.set_env(make_env())
    reference.env.seed(reference.seed)
    reference.learn(192, reset_num_timesteps=False)

    resumed = PPOPeVFA.load(tmp_path / "model", env=make_env(), restore_rng_state=True)
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # the history of the model's own moment: nothing to warn of
        resumed.load_history(tmp_path / "history")
    resumed.learn(192, reset_num_timesteps=False)
    assert resumed.history.policy_ids == reference.history.policy_ids
    for got, want in zip(resumed.history.samples(), reference.history.samples()):
        np.testing.assert_array_equal(got, want)
    np.testing.assert_array_equal(_final_state(resumed), _final_state(reference))
    # resuming without the history is another run
    no_history = PPOPeVFA.load(tmp_path / "model", env=make_env(), restore_rng_state=True)
    no_history.learn(192, reset_num_timesteps=False)
    assert not np.array_equal(_final_state(no_history), _final_state(reference))


@pytest.mark.parametrize("seed", [0, None])
def test_load_leaves_the_callers_rng_as_sb3_does(tmp_path, seed):
    """By default load does not bring the saving process's global RNG states: after it, the caller's RNGs are where
    SB3's own load leaves them, whatever the saving process had drawn."""
    model = PPOPeVFA("MlpPolicy", "Pendulum-v1", **{**FAST, "seed": seed})
    model.learn(64)
    th.manual_seed(1), np.random.seed(1)
    model.save(tmp_path / "a")
    th.manual_seed(2), np.random.seed(2)
    model.save(tmp_path / "b")

    def after_load(name, **kwargs):
        th.manual_seed(3), np.random.seed(3)
        PPOPeVFA.load(tmp_path / name, **kwargs)
        return th.rand(3), np.random.rand(3)

    for got, want in zip(after_load("a"), after_load("b")):
        np.testing.assert_array_equal(got, want)
    # opt-in: the saving process's states
    th.manual_seed(1), np.random.seed(1)
    expected = th.rand(3), np.random.rand(3)
    for got, want in zip(after_load("a", restore_rng_state=True), expected):
        np.testing.assert_array_equal(got, want)


@pytest.mark.parametrize("rollout_encoder_gradient", [True, False])
def test_value_loss_trains_encoder_and_not_actor(rollout_encoder_gradient):
    model = PPOPeVFA(
        "MlpPolicy", "Pendulum-v1", representation="opr", rollout_encoder_gradient=rollout_encoder_gradient, **FAST
    )
    model.learn(192)
    policy = model.policy
    # gradient of the on-policy value loss: reaches the critic, never the actor; the encoder only if asked to
    policy.set_training_mode(True)
    data = next(model.rollout_buffer.get(64))
    values, _, _ = policy.evaluate_actions(data.observations, data.actions)
    policy.optimizer.zero_grad()
    th.nn.functional.mse_loss(values.flatten(), data.returns).backward()
    actor = [*policy.mlp_extractor.policy_net.parameters(), *policy.action_net.parameters(), policy.log_std]
    assert all(p.grad is None or not p.grad.any() for p in actor)
    assert all(p.grad is not None and p.grad.abs().sum() > 0 for p in policy.value_net.parameters())
    encoder_grads = [p.grad is not None and p.grad.abs().sum() > 0 for p in policy.representation.parameters()]
    assert encoder_grads == [rollout_encoder_gradient] * len(encoder_grads)
    # historical updates change the encoder and the critic, and leave the actor as it was
    actor_before, encoder_before = actor_parameters(policy), module_parameters(policy.representation)
    critic_before = module_parameters(policy.value_net)
    model._history_credit = 10 * model.history_train_freq
    losses = model._train_on_history()
    assert len(losses) > 0
    assert th.equal(actor_parameters(policy), actor_before)
    assert not th.equal(module_parameters(policy.representation), encoder_before)
    assert not th.equal(module_parameters(policy.value_net), critic_before)


@pytest.mark.parametrize("update_order", ["joint", "critic_first"])
def test_without_rollout_gradient_the_on_policy_update_reads_the_moved_encoder_and_leaves_it(update_order):
    """``rollout_encoder_gradient=False`` (default): the on-policy update reads chi of the encoder as the historical
    updates left it (not a chi cached before them), without gradient, and does not change the encoder."""
    model = PPOPeVFA("MlpPolicy", "Pendulum-v1", update_order=update_order, **FAST)
    model.learn(128)
    policy, calls = model.policy, []
    on_policy = model._train_critic_on_rollout if update_order == "critic_first" else model._train_actor_critic
    embedding, history = policy.behaviour_embedding, model._train_on_history

    def spy_history():
        calls.append(("before history", module_parameters(policy.representation)))
        return history()

    def spy_embedding():
        chi = embedding()
        calls.append(("chi", chi))
        return chi

    def spy_on_policy():
        with th.no_grad():
            calls.append(("expected", policy.embed(policy.behaviour_record()), module_parameters(policy.representation)))
        policy.behaviour_embedding = spy_embedding
        try:
            return on_policy()
        finally:
            del policy.behaviour_embedding
            calls.append(("after", module_parameters(policy.representation)))

    model._train_on_history = spy_history
    setattr(model, "_train_critic_on_rollout" if update_order == "critic_first" else "_train_actor_critic", spy_on_policy)
    model.learn(64, reset_num_timesteps=False)
    (_, before), (_, expected, encoder) = calls[0], calls[1]
    assert not th.equal(before, encoder)  # the historical updates moved the encoder ...
    chis = [call[1] for call in calls if call[0] == "chi"]
    assert len(chis) >= 4 and all(th.equal(chi, expected) and not chi.requires_grad for chi in chis)  # ... chi is theirs
    assert th.equal(calls[-1][1], encoder)  # and the on-policy update left it


def test_the_encoder_learns_from_the_rollout_where_nothing_else_trains_it():
    """``rollout_encoder_gradient=None`` (default): off while historical updates train the encoder, on without them
    (``history_train_freq=0``), where the encoder would otherwise never learn; an explicit value wins, also when it
    is changed on a built model."""
    assert not PPOPeVFA("MlpPolicy", "Pendulum-v1", **FAST).trains_encoder_on_rollout
    model = PPOPeVFA("MlpPolicy", "Pendulum-v1", **{**FAST, "history_train_freq": 0})
    assert model.trains_encoder_on_rollout and model.policy.behaviour_chi_gradient
    encoder = module_parameters(model.policy.representation)
    model.learn(128)
    assert not th.equal(module_parameters(model.policy.representation), encoder)  # the on-policy loss trained it
    model.rollout_encoder_gradient = False
    encoder = module_parameters(model.policy.representation)
    model.learn(128, reset_num_timesteps=False)
    assert not model.policy.behaviour_chi_gradient
    assert th.equal(module_parameters(model.policy.representation), encoder)  # nothing trains it now


def test_critic_frozen_for_actor_update_in_critic_first_order(csv_logger):
    model = PPOPeVFA("MlpPolicy", "Pendulum-v1", update_order="critic_first", **FAST)
    model.set_logger(csv_logger[0])
    model.learn(128)
    policy = model.policy

    def critic():
        return th.cat([p.detach().flatten().clone() for p in policy.critic_parameters()])

    critic_before, actor_before = critic(), actor_parameters(policy)
    with policy.critic_frozen():
        policy.set_training_mode(True)
        values, _, _ = policy.evaluate_actions(*next(model.rollout_buffer.get(32))[:2])
        assert not values.requires_grad
        # SB3's PPO update in this context moves the actor and leaves the whole critic (streams, head, encoder)
        PPO.train(model)
    assert th.equal(critic(), critic_before) and not th.equal(actor_parameters(policy), actor_before)
    # the critic's own epochs on the rollout: n_epochs x (64 / 32) steps, logged as their mean loss
    losses = model._train_critic_on_rollout()
    assert len(losses) == model.n_epochs * 2 and not th.equal(critic(), critic_before)
    logged = [float(row["pevfa/critic_value_loss"]) for row in read_progress(csv_logger[1])[1:]]
    assert len(logged) == 1 and logged[0] > 0


def test_critic_first_recomputes_advantages_with_updated_critic():
    model = PPOPeVFA("MlpPolicy", "Pendulum-v1", update_order="critic_first", **FAST)
    model.learn(64)
    _, callback = model._setup_learn(64, reset_num_timesteps=False)
    model.collect_rollouts(model.env, callback, model.rollout_buffer, model.n_steps)
    buffer = model.rollout_buffer
    values_before, advantages_before = buffer.values.copy(), buffer.advantages.copy()
    model._train_critic_on_rollout()
    model._recompute_advantages()
    assert not np.allclose(buffer.values, values_before)
    model.policy.set_training_mode(False)
    with th.no_grad():
        observations = flat_observations(buffer, model.device, env_major=False)
        expected = model.policy.predict_values(observations).numpy().reshape(values_before.shape)
        last = model.policy.predict_values(th.as_tensor(model._last_obs)).numpy().flatten()
    np.testing.assert_allclose(buffer.values, expected, rtol=1e-6)
    # GAE written out, with the updated critic's values and its value of the state after the rollout
    gamma, lam, gae = model.gamma, model.gae_lambda, 0.0
    advantages = np.zeros_like(buffer.values)
    for t in reversed(range(model.n_steps)):
        if t == model.n_steps - 1:
            not_done, next_value = 1.0 - model._last_episode_starts, last
        else:
            not_done, next_value = 1.0 - buffer.episode_starts[t + 1], buffer.values[t + 1]
        gae = buffer.rewards[t] + gamma * next_value * not_done - buffer.values[t] + gamma * lam * not_done * gae
        advantages[t] = gae
    np.testing.assert_allclose(buffer.advantages, advantages, rtol=1e-5, atol=1e-6)
    np.testing.assert_allclose(buffer.returns, advantages + buffer.values, rtol=1e-5, atol=1e-6)
    assert not np.allclose(buffer.advantages, advantages_before)


def test_value_target_lambda_gives_monte_carlo_returns():
    obs_space, act_space = gym.spaces.Box(-1, 1, (1,)), gym.spaces.Box(-1, 1, (1,))
    buffers = {
        lam: PeVFARolloutBuffer(5, obs_space, act_space, gamma=0.9, gae_lambda=0.5, value_target_lambda=lam)
        for lam in (None, 1.0)
    }
    sb3 = RolloutBuffer(5, obs_space, act_space, gamma=0.9, gae_lambda=0.5)
    rewards = [1.0, 2.0, 3.0, 4.0, 5.0]
    for buffer in [*buffers.values(), sb3]:
        for t, r in enumerate(rewards):
            buffer.add(np.zeros((1, 1)), np.zeros((1, 1)), np.array([r]), np.array([t == 3]), th.tensor([0.5]), th.zeros(1))
        buffer.compute_returns_and_advantage(last_values=th.tensor([10.0]), dones=np.array([False]))
    np.testing.assert_allclose(buffers[None].returns, sb3.returns)
    np.testing.assert_allclose(buffers[1.0].advantages, sb3.advantages)
    # episode boundary before step 3: Monte-Carlo returns of steps 0-2, then 3-4 bootstrapped with 10
    mc = [1 + 0.9 * 2 + 0.81 * 3, 2 + 0.9 * 3, 3, 4 + 0.9 * (5 + 0.9 * 10), 5 + 0.9 * 10]
    np.testing.assert_allclose(buffers[1.0].returns.flatten(), mc, rtol=1e-5)


def test_separate_critic_learning_rate(csv_logger):
    model = PPOPeVFA(
        "MlpPolicy", "CartPole-v1", learning_rate=1e-4, critic_learning_rate=lambda progress: 1e-3 * progress, **FAST
    )
    model.set_logger(csv_logger[0])
    model.learn(128)
    groups = {g["name"]: g["lr"] for g in model.policy.optimizer.param_groups}
    # the schedules are at progress 0 after the last update
    assert groups["actor"] == pytest.approx(1e-4) and groups["critic"] == 0.0
    rows = read_progress(csv_logger[1])
    assert float(rows[1]["pevfa/critic_learning_rate"]) == pytest.approx(1e-3 * 0.5)
    critic = {id(p) for p in model.policy.critic_parameters()}
    assert critic == {id(p) for p in model.policy.optimizer.param_groups[1]["params"]}
    assert {id(p) for p in model.policy.representation.parameters()} <= critic
    assert not {id(p) for p in model.policy.action_net.parameters()} & critic


def test_none_is_a_conventional_critic_through_the_same_path():
    model = PPOPeVFA("MlpPolicy", "CartPole-v1", representation="none", **FAST)
    head = model.policy.value_net
    assert head.embedding_net is None and model.policy.representation.embedding_dim == 0
    assert len(list(model.policy.representation.parameters())) == 0
    model.learn(128)
    policy = model.policy
    policy.set_training_mode(False)
    obs = th.as_tensor(np.stack([model.observation_space.sample() for _ in range(5)]))
    with th.no_grad():
        plain = head.output(head.hidden(policy.mlp_extractor.forward_critic(obs)))
        assert th.equal(policy.predict_values(obs), plain)
        assert th.equal(policy.predict_values(obs, th.zeros(5, 0)), plain)


def test_history_bounds_during_training():
    model = PPOPeVFA("MlpPolicy", "CartPole-v1", history_buffer_size=100, history_max_policies=3, **FAST)
    model.learn(320)
    # five rollouts (policies 0-4) and the final record 5: the newest three stay, and the newest 100 samples
    assert model.history.policy_ids == [3, 4, 5]
    _, targets, ids = model.history.samples()
    assert ids.tolist() == [3] * 36 + [4] * 64
    np.testing.assert_array_equal(targets[-64:], model.rollout_buffer.returns.flatten())


@pytest.mark.parametrize("batch_policies", [None, 2])
def test_sampled_history_batches_are_the_samples_of_their_policies(batch_policies):
    """Each batch of the historical updates: samples of earlier policies only (never the one that collected the
    current rollout), each with the observation and value target its policy's rollout gave, and a loss computed with
    the chi of that very policy (``random`` codes: chi far apart for every policy, so a mix-up shows in the loss).
    Grouped batches (``history_batch_policies``) hold that many policies at most; None: uniform samples."""
    model = PPOPeVFA(
        "MlpPolicy",
        "Pendulum-v1",
        representation="random",
        history_batch_size=64,
        history_batch_policies=batch_policies,
        **FAST,
    )
    rollouts, batches = {}, []
    add_rollout, critic_step = model.recorder.add_rollout, model._critic_step
    sampler = "sample" if batch_policies is None else "sample_grouped"
    sample = getattr(model.history, sampler)

    def spy_rollout(buffer, policy_id, *args, **kwargs):
        rollouts[policy_id] = (buffer.observations.reshape(-1, 3).copy(), buffer.returns.reshape(-1).copy())
        add_rollout(buffer, policy_id, *args, **kwargs)

    def spy_sample(n, *args, **kwargs):
        batch = sample(n, *args, **kwargs)
        exclude_policy = kwargs.get("exclude_policy", args[-1] if args else None)
        batches.append([exclude_policy, batch, None])
        return batch

    def spy_step(loss, what):
        if what == "historical value loss":  # the loss the batch gave, recomputed from the records
            _, (obs, targets, ids), _ = batches[-1]
            with th.no_grad():
                chi = th.cat([model.policy.embed(PolicyRecord.from_numpy(model.history.records([i]))) for i in ids])
                values = model.policy.predict_values(th.as_tensor(obs), chi).flatten()
                batches[-1][2] = (loss.item(), th.mean((values - th.as_tensor(targets)) ** 2).item())
        return critic_step(loss, what)

    model.recorder.add_rollout, model._critic_step = spy_rollout, spy_step
    setattr(model.history, sampler, spy_sample)
    model.learn(320)
    assert [batch is None for _, batch, _ in batches] == [True] + [False] * 16  # 4 per update from the second on
    distinct = []
    for exclude, (obs, targets, ids), (loss, recomputed) in batches[1:]:
        assert exclude in rollouts and exclude not in ids and set(ids) <= set(rollouts)
        distinct.append(len(np.unique(ids)))
        for o, target, policy_id in zip(obs, targets, ids):
            rollout_obs, rollout_targets = rollouts[policy_id]
            (row,) = np.flatnonzero((rollout_obs == o).all(axis=1))
            assert rollout_targets[row] == target
        assert loss == pytest.approx(recomputed, rel=1e-5)
    assert max(distinct) == (4 if batch_policies is None else 2)  # uniform: all 4 earlier policies in the last batches


@pytest.mark.parametrize("algo", [PPO, A2C])
def test_history_callback_on_plain_sb3(tmp_path, algo):
    model = algo("MlpPolicy", "CartPole-v1", n_steps=32, seed=0)
    callback = PolicyHistoryCallback(n_state_action_pairs=10)
    model.learn(128, callback=callback)
    history = callback.history
    assert history.n_policies == 128 // (32 * model.n_envs) + 1 and history.n_samples == 128
    assert history.records(history.policy_ids)["states"].shape[1:] == (10, 4)
    # the final record is the trained policy
    live = ActorLayout.from_policy(model.policy).flatten(model.policy).numpy()
    np.testing.assert_array_equal(history.records([history.latest_policy_id])["params"][0], live)
    # the last rollout's samples with their value targets
    np.testing.assert_array_equal(history.samples()[1][-32:], model.rollout_buffer.returns.flatten())
    # each rollout's record at its first step, with the mean return of the episodes that ended in that rollout
    info = [history.record_info(i) for i in history.policy_ids]
    assert [record["num_timesteps"] for record in info] == [0, 32, 64, 96, 128]
    ends = np.cumsum([episode["l"] for episode in model.ep_info_buffer])  # one env: each episode's last step
    returns = np.array([episode["r"] for episode in model.ep_info_buffer])
    assert len(ends) > 2 and ends[-1] <= 128
    for k, record in enumerate(info[:-1]):
        ended = returns[(ends > 32 * k) & (ends <= 32 * (k + 1))]
        assert record.get("episode_return") == (pytest.approx(ended.mean()) if len(ended) else None), k
    history.save(tmp_path / "h")
    loaded = PolicyHistory(model.observation_space, model.action_space, history.n_params, 10).load(tmp_path / "h")
    assert loaded.policy_ids == history.policy_ids
    for got, want in zip(loaded.samples(), history.samples()):
        np.testing.assert_array_equal(got, want)


def test_bad_input_errors():
    env = "CartPole-v1"
    cases = [
        (dict(representation="opr_cl"), ValueError, "valid choices"),
        (dict(update_order="actor_first"), ValueError, "valid choices"),
        (dict(embedding_dim=0), ValueError, "embedding_dim"),
        (dict(history_buffer_size=0), ValueError, "history_buffer_size"),
        (dict(history_max_policies=-2), ValueError, "history_max_policies"),
        (dict(history_batch_size=0), ValueError, "history_batch_size"),
        (dict(history_train_freq=-1), ValueError, "history_train_freq"),
        (dict(history_batch_policies=0), ValueError, "history_batch_policies"),
        (dict(history_batch_policies=2.5), ValueError, "history_batch_policies"),
        (dict(history_batch_policies=True), ValueError, "history_batch_policies"),
        (dict(rollout_encoder_gradient="yes"), TypeError, "rollout_encoder_gradient"),
        (dict(fast_path=None), TypeError, "fast_path"),
        (dict(flush_denormal="yes"), TypeError, "flush_denormal"),
        (dict(n_state_action_pairs=-1), ValueError, "n_state_action_pairs"),
        (dict(representation="spr", n_state_action_pairs=0), ValueError, "n_state_action_pairs"),
        (dict(critic_learning_rate=-1.0), ValueError, "critic_learning_rate"),
        (dict(critic_learning_rate=float("nan")), ValueError, "critic_learning_rate"),
        (dict(critic_learning_rate=float("inf")), ValueError, "critic_learning_rate"),
        (dict(n_steps=64, history_buffer_size=64), ValueError, "holds no more than one rollout"),
        (dict(value_target_lambda=1.5), ValueError, "value_target_lambda"),
        (dict(policy_kwargs=dict(representation="spr")), ValueError, "policy_kwargs"),
        (dict(policy_kwargs=dict(critic_combine="hyper")), ValueError, "valid choices"),
        (dict(policy_kwargs=dict(critic_head_arch=[0])), ValueError, "positive"),
        (dict(value_target_lambda=1.0, rollout_buffer_class=RolloutBuffer), ValueError, "PeVFARolloutBuffer"),
    ]
    for kwargs, error, match in cases:
        with pytest.raises(error, match=match):
            PPOPeVFA("MlpPolicy", env, **kwargs)
    with pytest.raises(TypeError, match="PeVFA policy"):
        PPOPeVFA(ActorCriticPolicy, env)
    with pytest.raises(ValueError, match=r"^Unknown policy 'LstmPolicy' for PPOPeVFA, valid choices: \['CnnPolicy', 'Mlp"):
        PPOPeVFA("LstmPolicy", env)

    class TupleActions(gym.Env):
        observation_space = gym.spaces.Box(-1, 1, (2,))
        action_space = gym.spaces.Tuple([gym.spaces.Discrete(2), gym.spaces.Discrete(2)])

    with pytest.raises(TypeError, match="action spaces"):
        PPOPeVFA("MlpPolicy", TupleActions())

    class TupleObservations(gym.Env):
        observation_space = gym.spaces.Tuple([gym.spaces.Discrete(2), gym.spaces.Discrete(2)])
        action_space = gym.spaces.Discrete(2)

    with pytest.raises(TypeError, match="observation space"):
        PPOPeVFA("MlpPolicy", TupleObservations())


def test_policy_without_record_uses_live_parameters():
    model = PPOPeVFA("MlpPolicy", "Pendulum-v1", **FAST)
    obs = th.ones(3, 3)
    policy = model.policy
    policy.set_training_mode(False)
    live = PolicyRecord(policy.layout.flatten(policy)[None], th.zeros(1, 0, 3), th.zeros(1, 0, 1), th.zeros(1, 0))
    with th.no_grad():
        np.testing.assert_allclose(policy.predict_values(obs), policy.predict_values(obs, policy.embed(live)), rtol=1e-6)
        before = policy.predict_values(obs).clone()
        policy.action_net.bias.add_(1.0)  # not cached: the values follow the live actor
        assert not th.allclose(policy.predict_values(obs), before)
    spr = PPOPeVFA("MlpPolicy", "Pendulum-v1", representation="spr", **FAST)
    with pytest.raises(RuntimeError, match="recorded policy"):
        spr.policy.predict_values(obs)
    assert isinstance(model.policy, PeVFAActorCriticPolicy)


def test_user_workflow_from_the_readme(tmp_path):
    """The README's snippet on a MuJoCo task, at a tiny budget."""
    model = PPOPeVFA("MlpPolicy", "InvertedPendulum-v5", representation="opr", verbose=1, **FAST)
    model.learn(128, progress_bar=True)
    model.save(tmp_path / "hopper")
    model.save_history(tmp_path / "hopper_history")
    model = PPOPeVFA.load(tmp_path / "hopper", env=None)
    assert model.env is None
    model.load_history(tmp_path / "hopper_history")
    model.learn(64, reset_num_timesteps=False)
    assert model.num_timesteps == 192 and model.history.n_policies == 4


@pytest.mark.parametrize("env_id", ["CartPole-v1", "Pendulum-v1"])
def test_without_representation_and_history_it_is_sb3_ppo(env_id):
    """No representation, no historical updates, SB3's critic shape: PPOPeVFA trains exactly as SB3's PPO."""
    common = dict(n_steps=64, batch_size=32, n_epochs=3, seed=0, policy_kwargs=dict(net_arch=dict(pi=[32, 32], vf=[32, 32])))
    ppo = PPO("MlpPolicy", env_id, **common)
    policy_kwargs = {**common["policy_kwargs"], "critic_head_arch": []}
    sb3_twin_runs(ppo, PPOPeVFA("MlpPolicy", env_id, **{**common, **AS_SB3, "policy_kwargs": policy_kwargs}), 192)


def test_the_critic_reads_chi_from_its_arguments():
    model = PPOPeVFA("MlpPolicy", "Pendulum-v1", **FAST)
    model.learn(128)
    policy, history = model.policy, model.history
    policy.set_training_mode(False)
    obs = th.as_tensor(np.stack([model.observation_space.sample() for _ in range(6)]))
    records = PolicyRecord.from_numpy(history.records(history.policy_ids))
    chi = policy.embed(records)
    with th.no_grad():
        # the default chi is the behaviour policy's: the latest record, after learn() the trained policy
        np.testing.assert_allclose(policy.predict_values(obs), policy.predict_values(obs, chi[-1:]), rtol=1e-5, atol=1e-6)
        first, last = policy.predict_values(obs, chi[:1]), policy.predict_values(obs, chi[-1:])
        assert (first - last).abs().max() > 1e-5  # V depends on which policy chi describes (untrained: 1e-4 apart)
        per_row = policy.predict_values(obs[:2], chi[[0, -1]])  # one chi per observation
        np.testing.assert_allclose(per_row.flatten(), [first[0, 0], last[1, 0]], rtol=1e-5, atol=1e-6)
        actions, values, _ = policy(obs, deterministic=True, chi=chi[:1])
        np.testing.assert_allclose(values, first, rtol=1e-6)
        values, _, _ = policy.evaluate_actions(obs, actions, chi=chi[:1])
        np.testing.assert_allclose(values, first, rtol=1e-6)


def test_policy_pickles_copies_and_deepcopies_like_sb3():
    import copy
    import pickle

    model = PPOPeVFA("MlpPolicy", "Pendulum-v1", update_order="critic_first", **FAST)
    model.learn(128)
    obs = th.zeros(3, 3)
    policy = model.policy
    # as after a PPO step: the latest action distribution holds autograd tensors (SB3's policy then fails deepcopy)
    policy.evaluate_actions(obs, th.zeros(3, 1))
    assert policy.action_dist.distribution.loc.grad_fn is not None
    policy.set_training_mode(False)
    expected = policy.predict_values(obs).detach()
    with th.no_grad():
        actions = policy._predict(obs, deterministic=True)
    for clone in (pickle.loads(pickle.dumps(policy)), copy.deepcopy(policy)):
        clone.set_training_mode(False)
        np.testing.assert_array_equal(clone.predict_values(obs).detach(), expected)
        with th.no_grad():
            np.testing.assert_array_equal(clone._predict(obs, deterministic=True), actions)
        # a copy's frozen critic is its own
        with clone.critic_frozen():
            assert not clone.critic_trainable and policy.critic_trainable


def test_a_gsde_policy_samples_after_a_deepcopy():
    import copy

    model = PPOPeVFA("MlpPolicy", "Pendulum-v1", use_sde=True, **FAST).learn(128)  # its noise matrices carry a graph
    clone = copy.deepcopy(model.policy)
    obs = np.zeros((4, 3), np.float32)
    np.testing.assert_array_equal(clone.predict(obs, deterministic=True)[0], model.policy.predict(obs, deterministic=True)[0])
    th.manual_seed(0)
    sampled = clone.predict(obs, deterministic=False)[0]
    th.manual_seed(0)
    np.testing.assert_array_equal(sampled, model.policy.predict(obs, deterministic=False)[0])


def test_a_second_history_callback_does_not_touch_the_behaviour_record():
    model = PPOPeVFA("MlpPolicy", "Pendulum-v1", representation="spr", **FAST)
    extra = PolicyHistoryCallback(n_state_action_pairs=200)
    model.learn(128, callback=extra)
    # the callback keeps its own history of the same policies (its own probe states); the critic's record is the model's
    assert extra.history.n_policies == model.history.n_policies == 3
    ours, theirs = (h.records([h.latest_policy_id]) for h in (model.history, extra.history))
    np.testing.assert_array_equal(ours["params"], theirs["params"])
    np.testing.assert_array_equal(model.policy.behaviour_states.numpy(), ours["states"][0])
    assert not np.array_equal(ours["states"], theirs["states"])


def test_gsde_probe_actions_have_their_own_noise():
    """Each probe state of a gSDE policy's record gets its own exploration noise (not one matrix for all)."""
    from sb3_pevfa.pevfa.records import record_policy

    model = PPOPeVFA("MlpPolicy", "Pendulum-v1", representation="spr", use_sde=True, **FAST)
    policy = model.policy
    same_state = np.repeat(model.observation_space.sample()[None], 20, axis=0)
    actions = record_policy(policy, policy.layout, same_state, np.zeros(0))["actions"]
    assert len(np.unique(actions)) == 20  # one shared exploration matrix gives 20 equal actions at one state


def test_objective_gradients_do_not_reach_the_next_update():
    kwargs = {name: dict(learning_starts=0, train_freq=32) for name in ("cl", "aux")}
    model = PPOPeVFA("MlpPolicy", "CartPole-v1", representation="spr", representation_objectives=("cl", "aux"),
                     objective_kwargs=kwargs, **FAST)  # fmt: skip
    model.learn(192)
    assert model.logger.name_to_value["pevfa/cl_updates"] == 2
    own = [p for objective in model.policy.objectives.values() for p in objective.parameters() if p.requires_grad]
    assert own and all(p.grad is None for p in own)


def test_loading_weights_drops_the_cached_chi(tmp_path):
    first = PPOPeVFA("MlpPolicy", "Pendulum-v1", **FAST).learn(128)
    second = PPOPeVFA("MlpPolicy", "Pendulum-v1", **{**FAST, "seed": 1}).learn(128)
    obs = th.zeros(2, 3)
    first.policy.set_training_mode(False)
    first.policy.predict_values(obs)  # chi of the behaviour record cached
    first.set_parameters(second.get_parameters())
    second.policy.set_training_mode(False)
    np.testing.assert_allclose(first.policy.predict_values(obs).detach(), second.policy.predict_values(obs).detach())


def test_log_interval_defaults_to_the_base_algorithms():
    from stable_baselines3.common.logger import configure

    from sb3_pevfa import A2CPeVFA

    dumps = {}
    for algo in (PPOPeVFA, A2CPeVFA):
        model = algo("MlpPolicy", "CartPole-v1", n_steps=8, **({"batch_size": 8, "n_epochs": 1} if algo is PPOPeVFA else {}))
        model.set_logger(configure(None, []))
        counts = []
        model.logger.dump = lambda step=0, counts=counts: counts.append(step)
        model.learn(8 * 150)
        dumps[algo] = len(counts)
    assert dumps == {PPOPeVFA: 150, A2CPeVFA: 1}  # SB3: PPO logs every iteration, A2C every 100


@pytest.mark.parametrize("fast_path", [True, False])
@pytest.mark.parametrize("env_id", ["Pendulum-v1", "CartPole-v1"])
def test_a_nan_actor_stops_the_run_at_once(env_id, fast_path):
    """No silent NaN run: a NaN in the actor is refused when the policy is recorded, before it acts; a NaN that
    reaches the action distribution (from an observation) fails its argument check, as in SB3 PPO, on both paths."""
    model = PPOPeVFA("MlpPolicy", env_id, fast_path=fast_path, **FAST)
    model.learn(64)
    with th.no_grad():
        model.policy.action_net.weight[0, 0] = float("nan")
    with pytest.raises(ValueError, match=r"non-finite policy record field 'params': nan"):
        model.learn(64, reset_num_timesteps=False)

    class NaNAfter(gym.Wrapper):
        steps = 0

        def step(self, action):
            observation, *rest = self.env.step(action)
            self.steps += 1
            return (observation * np.nan if self.steps > 40 else observation), *rest

    for algo, kwargs in ((PPO, dict(n_steps=64, batch_size=32, seed=0)), (PPOPeVFA, dict(**FAST, fast_path=fast_path))):
        model = algo("MlpPolicy", NaNAfter(gym.make(env_id)), **kwargs)
        with pytest.raises(ValueError, match=r"Expected parameter (loc|logits)"):
            model.learn(64)
        assert model.num_timesteps == 41  # stopped at the first action that would read a NaN observation


def test_a_nan_critic_stops_the_critic_steps_before_they_spread_it():
    model = PPOPeVFA("MlpPolicy", "Pendulum-v1", update_order="critic_first", **FAST)
    model.learn(128)
    with th.no_grad():
        model.policy.value_net.output.bias.fill_(float("inf"))
    encoder = module_parameters(model.policy.representation)
    model._history_credit = 4 * model.history_train_freq
    with pytest.raises(ValueError, match=r"historical value loss is (nan|inf)"):
        model._train_on_history()
    with pytest.raises(ValueError, match=r"critic-first epochs is (nan|inf)"):
        model._train_critic_on_rollout()
    assert th.equal(module_parameters(model.policy.representation), encoder)  # no step spread it


def test_the_default_critic_reads_a_layer_normalised_chi_through_relus():
    """The default embedding stream (the ablation's choice, docs/notes/2026-12-02-critic-and-target-ablation.md): chi
    layer-normalised, then ReLU layers, so V depends on chi's direction and not on its scale, which had driven the Tanh
    stream flat."""
    model = PPOPeVFA("MlpPolicy", "Pendulum-v1", **FAST).learn(128)
    policy, head = model.policy, model.policy.value_net
    assert isinstance(head.chi_norm, th.nn.LayerNorm) and any(isinstance(m, th.nn.ReLU) for m in head.embedding_net)
    policy.set_training_mode(False)
    obs = th.as_tensor(np.stack([model.observation_space.sample() for _ in range(4)]))
    with th.no_grad():
        chi = policy.behaviour_embedding().expand(4, -1)
        # (10x: LayerNorm's epsilon no longer matters against chi's variance)
        large, small = policy.predict_values(obs, 1e4 * chi), policy.predict_values(obs, 10 * chi)
        np.testing.assert_allclose(large, small, rtol=1e-5, atol=1e-6)
        assert not th.allclose(policy.predict_values(obs, -chi), policy.predict_values(obs, chi))
    paper = PPOPeVFA("MlpPolicy", "Pendulum-v1", policy_kwargs=dict(chi_normalization="none"), **FAST)
    assert isinstance(paper.policy.value_net.chi_norm, th.nn.Identity)
    with th.no_grad():  # without the normalisation the scale of chi reaches V
        chi = paper.policy.behaviour_embedding().expand(4, -1)
        assert not th.allclose(paper.policy.predict_values(obs, 1e3 * chi), paper.policy.predict_values(obs, chi))
    with pytest.raises(ValueError, match="one-dimensional chi is constant: use 'none'"):
        PPOPeVFA("MlpPolicy", "Pendulum-v1", embedding_dim=1, **FAST)
    with pytest.raises(ValueError, match=r"valid choices: \('none', 'layernorm'\)"):
        PPOPeVFA("MlpPolicy", "Pendulum-v1", policy_kwargs=dict(chi_normalization="batchnorm"), **FAST)


def test_models_load_with_the_critic_they_were_saved_with(tmp_path):
    """New models save their critic's stream in policy_kwargs; a file without it (saved before 0.1.0 wrote it) is
    of the earlier stream, the actor's Tanh over chi as it is, whatever today's default."""
    model = PPOPeVFA("MlpPolicy", "Pendulum-v1", **FAST)
    assert model.policy_kwargs["chi_normalization"] == "layernorm"
    assert model.policy_kwargs["critic_activation_fn"] is th.nn.ReLU
    model.save(tmp_path / "today")
    today = PPOPeVFA.load(tmp_path / "today")
    assert isinstance(today.policy.value_net.chi_norm, th.nn.LayerNorm)
    assert str(today.policy.value_net.embedding_net) == str(model.policy.value_net.embedding_net)  # ReLU layers
    stream = dict(critic_activation_fn=None, chi_normalization="none")
    earlier = PPOPeVFA("MlpPolicy", "Pendulum-v1", policy_kwargs=stream, **FAST)
    earlier.save(tmp_path / "earlier")
    old = PPOPeVFA.load(tmp_path / "earlier", custom_objects={"policy_kwargs": {}})  # as a file of 0.1.0's past reads
    assert isinstance(old.policy.value_net.chi_norm, th.nn.Identity)
    assert str(old.policy.value_net.embedding_net) == str(earlier.policy.value_net.embedding_net)  # Tanh layers
    for name, parameter in earlier.policy.state_dict().items():
        assert th.equal(parameter, old.policy.state_dict()[name]), name
    # the earlier variants that set one of the two keys keep the other's earlier value
    relu_only = PPOPeVFA.load(tmp_path / "earlier", custom_objects={"policy_kwargs": {"critic_activation_fn": th.nn.ReLU}})
    assert isinstance(relu_only.policy.value_net.chi_norm, th.nn.Identity)


def test_logs_that_show_whether_the_critic_tells_policies_apart(csv_logger):
    tanh_stream = dict(critic_activation_fn=None, chi_normalization="none")  # the actor's Tanh, chi unnormalised
    model = PPOPeVFA("MlpPolicy", "Pendulum-v1", policy_kwargs=tanh_stream, **FAST)
    model.set_logger(csv_logger[0])
    model.learn(128)
    last = read_progress(csv_logger[1])[-1]
    assert 0.0 <= float(last["pevfa/embedding_saturated_fraction"]) <= 1.0
    head, policy = model.policy.value_net, model.policy
    policy.set_training_mode(False)
    chi = policy.behaviour_embedding()
    # Tanh stream: a huge chi drives every unit to the flat ends, a chi that the first layer maps to 0 to none
    assert head.saturated_fraction(1e4 * th.sign(th.randn_like(chi))) > 0.9
    with th.no_grad():
        head.embedding_net[0].bias.zero_()
    assert head.saturated_fraction(th.zeros_like(chi)) == 0.0
    # dV/dchi: matches a central difference along chi's own direction, and is 0 once the stream ignores chi
    gradient = model.value_chi_gradient(n_states=1)
    obs = flat_observations(model.rollout_buffer, model.device, env_major=False)[:1]
    with th.no_grad():
        step = 1e-3 * chi / chi.norm()
        slope = (policy.predict_values(obs, chi + step) - policy.predict_values(obs, chi - step)).item() / 2e-3
    assert abs(slope) <= gradient * (1 + 1e-3) and gradient > 0
    with th.no_grad():
        head.embedding_net[0].weight.zero_()
    assert model.value_chi_gradient() == 0.0


def test_a_model_loads_with_the_papers_schedule(tmp_path):
    model = PPOPeVFA("MlpPolicy", "Pendulum-v1", **FAST)
    model.save(tmp_path / "model")
    loaded = PPOPeVFA.load(tmp_path / "model", **PAPER_SCHEDULE)  # e.g. a model saved before the cheaper schedule
    assert {name: getattr(loaded, name) for name in PAPER_SCHEDULE} == PAPER_SCHEDULE
    assert loaded.policy.behaviour_chi_gradient


def test_checkpoints_save_and_load_the_history_of_their_moment(tmp_path):
    """A CheckpointCallback (rl-zoo3's --save-freq builds one without save_replay_buffer) saves the history with
    each checkpoint; the checkpoint loads with it, and rl-zoo3's ``-i`` call with the run's final history
    (``replay_buffer.pkl``) gets the checkpoint's own."""
    model = PPOPeVFA("MlpPolicy", "Pendulum-v1", **FAST)
    model.learn(256, callback=[CheckpointCallback(save_freq=128, save_path=str(tmp_path), name_prefix="rl_model")])
    model.save_replay_buffer(tmp_path / "replay_buffer.pkl")  # the final one, as --save-replay-buffer writes it
    assert (tmp_path / "rl_model_replay_buffer_128_steps.pkl").exists()
    checkpoint = PPOPeVFA.load(tmp_path / "rl_model_128_steps.zip")
    at_128 = [i for i in model.history.policy_ids if model.history.record_info(i)["num_timesteps"] < 128]  # before it
    assert checkpoint.num_timesteps == 128 and checkpoint.history.policy_ids == at_128
    checkpoint.load_replay_buffer(tmp_path / "replay_buffer.pkl")  # what rl-zoo3's -i does
    assert checkpoint.history.policy_ids == at_128
    checkpoint.load_replay_buffer(tmp_path / "rl_model_replay_buffer_128_steps")  # SB3's name without its .pkl
    assert checkpoint.history.policy_ids == at_128
    final = PPOPeVFA.load(tmp_path / "rl_model_256_steps.zip")  # the last checkpoint, at the run's end
    final.load_replay_buffer(tmp_path / "replay_buffer.pkl")  # the run's own history, not the checkpoint's
    assert final.history.policy_ids == model.history.policy_ids
    with pytest.warns(UserWarning, match="recorded up to 256 steps, this model is at 128") as caught:
        checkpoint.load_history(tmp_path / "replay_buffer.pkl")
    (tmp_path / "rl_model_replay_buffer_128_steps.pkl").unlink()  # rl-zoo3's -i where no checkpoint history exists
    with pytest.warns(UserWarning, match="recorded up to 256 steps, this model is at 128") as through_alias:
        checkpoint.load_replay_buffer(tmp_path / "replay_buffer.pkl")
    for record in (caught, through_alias):  # the warning points at the user's call
        assert [w.filename for w in record if "recorded up to" in str(w.message)] == [__file__]
    assert checkpoint.history.policy_ids == model.history.policy_ids


def test_aux_without_state_action_pairs_is_refused_at_construction():
    images = make_vec_env(lambda: FakeImageEnv(screen_height=36, screen_width=36, n_channels=1), n_envs=1)
    with pytest.raises(ValueError, match="objective 'aux' predicts actions from state-action pairs, which image"):
        PPOPeVFA("CnnPolicy", images, representation_objectives=("aux",))
    with pytest.raises(ValueError, match="objective 'aux' needs state-action pairs: n_state_action_pairs must be > 0"):
        PPOPeVFA("MlpPolicy", "CartPole-v1", representation_objectives="aux", n_state_action_pairs=0)
    PPOPeVFA("CnnPolicy", images, representation_objectives=("cl",))  # the contrastive objective needs no pairs


@pytest.mark.parametrize("history_train_freq", [16, 0])
def test_a_model_loaded_without_its_history_says_so_once_when_it_learns(tmp_path, history_train_freq):
    model = PPOPeVFA("MlpPolicy", "CartPole-v1", **{**FAST, "history_train_freq": history_train_freq})
    model.learn(128)
    model.save(tmp_path / "model")
    model.save_history(tmp_path / "history")
    loaded = PPOPeVFA.load(tmp_path / "model", env=make_vec_env("CartPole-v1", n_envs=1, seed=1))
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        loaded.learn(64, reset_num_timesteps=False)
        loaded.learn(64, reset_num_timesteps=False)
    empty = [w for w in caught if "its policy history is empty" in str(w.message)]
    if history_train_freq == 0:  # nothing reads the history: nothing to say
        assert not empty
        return
    assert len(empty) == 1 and "model.load_history(path)" in str(empty[0].message)
    assert empty[0].filename == __file__  # the warning points at the user's learn()
    again = PPOPeVFA.load(tmp_path / "model", env=make_vec_env("CartPole-v1", n_envs=1, seed=1))
    again.load_history(tmp_path / "history")
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        again.learn(64, reset_num_timesteps=False)
    assert not [w for w in caught if "its policy history is empty" in str(w.message)]


def test_the_cached_chi_follows_every_write_to_the_encoder_and_the_record():
    model = PPOPeVFA("MlpPolicy", "CartPole-v1", **FAST).learn(128)
    policy = model.policy
    policy.set_training_mode(False)

    def fresh() -> th.Tensor:
        with th.no_grad():
            policy.representation.train(False)
            return policy.embed(policy.behaviour_record())

    cached = policy.behaviour_embedding()
    assert th.equal(cached, fresh()) and policy.behaviour_embedding() is cached  # a hit while nothing changed
    with th.no_grad():  # an edit in place
        next(policy.representation.parameters()).mul_(1.5)
    assert not th.equal(policy.behaviour_embedding(), cached)
    assert th.allclose(policy.behaviour_embedding(), fresh())
    vector = policy.parameters_to_vector()  # SB3's load_from_vector replaces the parameters' data
    policy.load_from_vector(vector * 0.5)
    assert th.allclose(policy.behaviour_embedding(), fresh())
    policy.to("cpu")
    policy.behaviour_params.add_(1.0)  # the behaviour record
    assert th.allclose(policy.behaviour_embedding(), fresh())


def test_switching_the_training_mode_sets_every_module_as_torch_does():
    model = PPOPeVFA("MlpPolicy", "CartPole-v1", representation_objectives=("cl",), **FAST)
    policy = model.policy
    for mode in (False, True, False):
        policy.set_training_mode(mode)
        assert {module.training for module in policy.modules()} == {mode}
    policy.extra = th.nn.Dropout()  # a module added afterwards is listed again
    policy.set_training_mode(True)
    assert policy.extra.training and {m.training for m in policy.modules()} == {True}
    with pytest.raises(ValueError, match="training mode is expected to be a bool"):
        policy.set_training_mode(1)

    class Recorded(th.nn.Linear):  # a module with its own train(): torch's recursion is kept for it
        def train(self, mode: bool = True):
            self.switched = mode
            return super().train(mode)

    policy.recorded = Recorded(2, 2)
    policy.set_training_mode(False)
    assert policy.recorded.switched is False and {m.training for m in policy.modules()} == {False}
    copied = copy.deepcopy(policy)
    copied.set_training_mode(True)
    assert {m.training for m in copied.modules()} == {True} and {m.training for m in policy.modules()} == {False}
