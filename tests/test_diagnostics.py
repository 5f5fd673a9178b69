import pathlib

import gymnasium as gym
import numpy as np
import pytest
import torch as th
from conftest import FAST, read_progress
from stable_baselines3.common.logger import configure
from torch.nn import functional as F

from sb3_pevfa import A2CPeVFA, PolicyRecord, PPOPeVFA
from sb3_pevfa.diagnostics import (
    LocalGeneralizationCallback,
    embedding_maps,
    plot_embedding_maps,
    plot_local_generalization,
    policy_embeddings,
    predict_policy_values,
    run_global_generalization,
    zero_shot,
)
from sb3_pevfa.diagnostics.global_generalization import (
    POLICY_LAYOUT,
    _PointWalkerPeVFA,
    collect_returns,
    policy_actions,
    synthesize_policies,
)
from sb3_pevfa.diagnostics.local_generalization import ERROR_KEYS, monte_carlo_returns, read_scalars
from sb3_pevfa.pevfa.representations import RawPolicyRepresentation

ROOT = pathlib.Path(__file__).resolve().parent.parent


def test_point_walker_dynamics_and_reward():
    env = gym.make("PointWalker-v0")
    obs, _ = env.reset(seed=0)
    x, y = obs[:2]
    assert np.allclose(obs[2:], [np.sin(np.arctan2(y, x)), np.cos(np.arctan2(y, x)), np.cos(x), np.cos(y)], atol=1e-6)
    obs2, reward, terminated, truncated, _ = env.step(np.array([2.0, -0.5]))  # clipped to [-1, 1]
    assert np.allclose(obs2[:2], [x + 1.0, y - 0.5], atol=1e-6)
    assert reward == pytest.approx((((x + 1) ** 2 - (y - 0.5) ** 2) - (x**2 - y**2)) / 10, rel=1e-5)
    steps = 1
    while not truncated:
        _, _, terminated, truncated, _ = env.step(env.action_space.sample())
        steps += 1
    assert steps == 10 and not terminated


def test_vectorised_rollouts_match_the_env():
    rng = np.random.default_rng(0)
    params = rng.normal(size=(3, POLICY_LAYOUT.n_params)).astype(np.float32)
    states, returns = collect_returns(params, n_trajectories=2, horizon=10, rng=np.random.default_rng(1))
    env = gym.make("PointWalker-v0").unwrapped
    for p in range(3):
        env.position = states[p, 0, 0, :2].astype(np.float64)
        env.steps, total = 0, 0.0
        obs = states[p, 0, 0]
        for step in range(10):
            assert np.allclose(obs, states[p, 0, step], atol=1e-5)
            obs, reward, *_ = env.step(policy_actions(params[p : p + 1], obs[None, None])[0, 0])
            total += reward
        assert total == pytest.approx(returns[p, 0, 0], rel=1e-4, abs=1e-4)


def test_global_generalization_learns_something():
    results = run_global_generalization(n_policies=300, n_trajectories=10, epochs=4, seed=0)
    assert [r.representation for r in results] == ["rpr", "opr"]
    variance = np.var(np.concatenate([r.true_test_values for r in results[:1]]))
    for result in results:
        assert np.isfinite(result.test_mse) and result.train_mse < variance
        assert len(result.predicted_test_values) == 60


def test_monte_carlo_returns_and_complete_episodes():
    rewards = np.array([[1.0], [1.0], [1.0], [1.0]])
    starts = np.array([[1.0], [0.0], [1.0], [0.0]])  # episodes: steps 0-1, then 2-3 (cut by the rollout end)
    returns, complete = monte_carlo_returns(rewards, starts, last_dones=np.array([False]), gamma=0.5)
    np.testing.assert_allclose(returns.flatten(), [1.5, 1.0, 1.5, 1.0])
    assert complete.flatten().tolist() == [True, True, False, False]
    _, complete = monte_carlo_returns(rewards, starts, last_dones=np.array([True]), gamma=0.5)
    assert complete.all()


def test_local_generalization_callback_and_plot(tmp_path):
    model = PPOPeVFA("MlpPolicy", "CartPole-v1", **FAST)
    model.set_logger(configure(str(tmp_path), ["csv"]))
    model.learn(320, callback=LocalGeneralizationCallback())
    rows = [row for row in read_progress(tmp_path) if row.get("pevfa/local_gen/pevfa_before")]
    assert len(rows) == 5  # every iteration, the last one at the end of training
    for row in rows:
        errors = {key: float(row[f"pevfa/local_gen/{key}"]) for key in ERROR_KEYS}
        assert all(np.isfinite(v) and v >= 0 for v in errors.values())
    # the side critic trains: its error moves after the update
    assert any(float(r["pevfa/local_gen/vfa_after"]) != float(r["pevfa/local_gen/vfa_before"]) for r in rows)
    assert [int(r["pevfa/local_gen/timesteps"]) for r in rows] == [64, 128, 192, 256, 320]
    png = plot_local_generalization(tmp_path, tmp_path / "plot.png")
    assert png.stat().st_size > 10_000
    with pytest.raises(TypeError, match="PPOPeVFA"):
        from stable_baselines3 import PPO

        PPO("MlpPolicy", "CartPole-v1", n_steps=64).learn(64, callback=LocalGeneralizationCallback())


def test_local_generalization_side_critic_learns_at_the_critics_rate():
    """The conventional critic of the comparison trains as PPOPeVFA's critic does (the paper: 1e-3, actor 1e-4)."""
    model = PPOPeVFA("MlpPolicy", "CartPole-v1", learning_rate=1e-4, critic_learning_rate=2e-3, **FAST)
    callback = LocalGeneralizationCallback()
    model.learn(128, callback=callback)
    assert callback.optimizer.param_groups[0]["lr"] == 2e-3


def test_read_scalars_from_tensorboard(tmp_path):
    pytest.importorskip("tensorboard")
    model = PPOPeVFA("MlpPolicy", "CartPole-v1", tensorboard_log=str(tmp_path), **FAST)
    model.set_logger(configure(str(tmp_path / "both"), ["csv", "tensorboard"]))
    model.learn(256, callback=LocalGeneralizationCallback())
    # every iteration, also the last one, whose dump shares its step with the one at the end of training
    from_events, from_csv = read_scalars(tmp_path / "both"), read_scalars(tmp_path / "both" / "progress.csv")
    for key in ("timesteps", "pevfa_before", "vfa_after"):
        values = from_events[f"pevfa/local_gen/{key}"]
        expected = from_csv[f"pevfa/local_gen/{key}"]
        np.testing.assert_allclose(values[np.isfinite(values)], expected[np.isfinite(expected)], rtol=1e-6)
    timesteps = from_events["pevfa/local_gen/timesteps"]
    assert timesteps[np.isfinite(timesteps)].tolist() == [64, 128, 192, 256]
    plot_local_generalization(next(tmp_path.iterdir()), tmp_path / "tb.png")


@pytest.mark.parametrize("representation", ["opr", "fingerprint"])
def test_embedding_maps(tmp_path, representation, monkeypatch):
    model = PPOPeVFA("MlpPolicy", "CartPole-v1", representation=representation, **FAST).learn(640)
    ids, embeddings = policy_embeddings(model)
    assert ids.tolist() == model.history.policy_ids
    model.policy.set_training_mode(False)
    with th.no_grad():
        one_by_one = [model.policy.embed(PolicyRecord.from_numpy(model.history.records([i]))) for i in ids]
    np.testing.assert_allclose(embeddings, th.cat(one_by_one).numpy(), rtol=1e-5, atol=1e-6)
    np.testing.assert_allclose(policy_embeddings(model, batch_size=3)[1], embeddings, rtol=1e-5, atol=1e-6)  # chunked
    assert any("episode_return" in model.history.record_info(int(i)) for i in ids)
    figures = []
    save = embedding_maps.save_figure
    monkeypatch.setattr(embedding_maps, "save_figure", lambda fig, png: figures.append(fig) or save(fig, png))
    assert plot_embedding_maps(model, tmp_path / "maps.png").stat().st_size > 10_000
    # the last record (the trained policy) has no episode yet: grey, and a legend says why
    by_return = figures[0].axes[0]
    assert [t.get_text() for t in by_return.get_legend().get_texts()] == ["no average return recorded"]
    assert figures[0].axes[1].get_legend() is None  # every policy has an iteration
    with pytest.raises(ValueError, match="none"):
        policy_embeddings(PPOPeVFA("MlpPolicy", "CartPole-v1", representation="none", **FAST).learn(192))


@pytest.mark.parametrize("representation", ["opr", "spr", "fingerprint", "rpr"])
def test_zero_shot_values(tmp_path, representation):
    model = PPOPeVFA("MlpPolicy", "Pendulum-v1", representation=representation, **FAST).learn(192)
    obs = np.stack([model.observation_space.sample() for _ in range(5)])
    model.policy.set_training_mode(False)
    with th.no_grad():
        expected = model.policy.predict_values(th.as_tensor(obs)).flatten().numpy()
    latest = {k: v[0] for k, v in model.history.records([model.history.latest_policy_id]).items()}
    # the model's own (final, recorded) policy: from its record, exactly the critic's values
    np.testing.assert_allclose(predict_policy_values(model, latest, obs), expected, rtol=1e-5)
    other = PPOPeVFA("MlpPolicy", "Pendulum-v1", representation=representation, **{**FAST, "seed": 3})
    other.save(tmp_path / "other")
    from_path = predict_policy_values(model, tmp_path / "other.zip", obs)
    assert from_path.shape == (5,) and not np.allclose(from_path, expected)
    if representation != "spr":  # deterministic records: the saved policy's values, however it is passed
        np.testing.assert_allclose(from_path, predict_policy_values(model, other, obs), rtol=1e-6)
        flat = other.policy.layout.flatten(other.policy).detach().numpy()
        np.testing.assert_allclose(from_path, predict_policy_values(model, flat, obs), rtol=1e-6)
    if representation != "spr":
        np.testing.assert_allclose(predict_policy_values(model, model, obs), expected, rtol=1e-5)
        np.testing.assert_allclose(predict_policy_values(model, latest["params"], obs), expected, rtol=1e-5)
    else:
        with pytest.raises(ValueError, match="bare parameter vector"):
            predict_policy_values(model, latest["params"], obs)
    with pytest.raises(ValueError, match="differs"):
        predict_policy_values(model, PPOPeVFA("MlpPolicy", "Pendulum-v1", policy_kwargs=dict(net_arch=[8])), obs)


@pytest.mark.parametrize("representation", ["opr", "spr", "random"])
def test_q_values_of_a_snapshot_as_the_docs_compute_them(representation):
    from sb3_pevfa import SACPeVFA

    tiny = dict(snapshot_freq=20, learning_starts=100, batch_size=32, policy_kwargs=dict(net_arch=[32, 32]), seed=0)
    model = SACPeVFA("MlpPolicy", "Pendulum-v1", representation=representation, n_state_action_pairs=16, **tiny)
    model.learn(200)
    with pytest.raises(TypeError, match=r"critic is Q\(s, a, chi\): chi = model.policy.critic.representation"):
        predict_policy_values(model, model.history.records([0]), np.zeros((1, 3), np.float32))
    latest = model.record_snapshot()  # the live actor, its states and its code: the critics' own chi
    data = model.replay_buffer.sample(64)
    model.policy.set_training_mode(False)
    critic = model.policy.critic
    with th.no_grad():
        values = {}
        for k in (0, latest):  # the docs' call
            chi = critic.representation(PolicyRecord.from_numpy(model.history.records([k]), model.device))
            values[k] = th.cat(critic(data.observations, data.actions, chi), dim=1)
        live = th.cat(critic(data.observations, data.actions), dim=1)
    th.testing.assert_close(values[latest], live)
    assert (values[0] - live).abs().max() > 1e-3  # the first snapshot's chi: other values
    assert model.history.policy_ids == list(range(7))  # at gradient steps 1, 20, ..., 100, and the one above


def test_zero_shot_values_of_a_saved_a2c_pevfa_or_sb3_model_read_from_its_path(tmp_path):
    from stable_baselines3 import A2C, PPO

    model = PPOPeVFA("MlpPolicy", "Pendulum-v1", **FAST).learn(192)
    obs = np.stack([model.observation_space.sample() for _ in range(5)])
    for seed, other_class in enumerate((A2CPeVFA, PPO, A2C)):
        other = other_class("MlpPolicy", "Pendulum-v1", seed=seed)
        other.save(tmp_path / "other")
        from_path = predict_policy_values(model, tmp_path / "other.zip", obs)
        np.testing.assert_allclose(from_path, predict_policy_values(model, other, obs), rtol=1e-6)


def test_embedding_maps_and_episode_returns_of_sacpevfa_snapshots(tmp_path):
    from stable_baselines3.common.callbacks import BaseCallback

    from sb3_pevfa import SACPeVFA

    class Episodes(BaseCallback):  # (env step, return) of every episode that ends
        def _on_step(self) -> bool:
            ended = [info["episode"]["r"] for info in self.locals["infos"] if "episode" in info]
            self.ended = [*getattr(self, "ended", []), *((self.num_timesteps, r) for r in ended)]
            return True

    model = SACPeVFA("MlpPolicy", "Pendulum-v1", learning_starts=100, batch_size=32, snapshot_freq=150,
                     policy_kwargs=dict(net_arch=[32, 32]), seed=0)  # fmt: skip
    episodes = Episodes()
    model.learn(1300, callback=episodes)
    ids, embeddings = policy_embeddings(model)
    steps = [model.history.record_info(int(i))["num_timesteps"] for i in ids]
    for k, policy_id in enumerate(ids[:-1]):  # each snapshot: the episodes that ended until the next one
        returns = [r for step, r in episodes.ended if steps[k] < step <= steps[k + 1]]
        info = model.history.record_info(int(policy_id))
        assert info.get("episode_return") == (pytest.approx(np.mean(returns)) if returns else None)
    assert sum("episode_return" in model.history.record_info(int(i)) for i in ids) >= 4
    critic = model.policy.critic
    critic.train(False)
    with th.no_grad():
        expected = critic.representation(PolicyRecord.from_numpy(model.history.records(ids))).numpy()
    np.testing.assert_allclose(embeddings, expected, atol=1e-6)
    assert plot_embedding_maps(model, tmp_path / "maps.png").exists()
    episodes.ended, last = [], model.history.latest_policy_id
    model.learn(700, callback=episodes)  # SB3 counts the episodes anew: so do the snapshots
    new = [i for i in model.history.policy_ids if i > last]
    steps = [model.history.record_info(i)["num_timesteps"] for i in new]
    returns = [r for step, r in episodes.ended if steps[0] < step <= steps[1]]
    assert model.history.record_info(new[0])["episode_return"] == pytest.approx(np.mean(returns))
    before = [r for step, r in episodes.ended if step <= steps[0]]  # the last snapshot acted until the first new one
    assert len(before) == 1 and model.history.record_info(last)["episode_return"] == pytest.approx(before[0])
    with pytest.raises(TypeError, match="Q\\(s, a, chi\\)"):
        predict_policy_values(model, model.policy, np.zeros((2, 3), np.float32))


def test_collect_returns_discounts_by_gamma():
    """Discounted by gamma per step (the default gamma=1 would hide a wrong power)."""
    params = synthesize_policies(2, np.random.default_rng(0))
    _, returns = collect_returns(params, n_trajectories=2, horizon=4, rng=np.random.default_rng(1), gamma=0.5)
    _, undiscounted = collect_returns(params, n_trajectories=2, horizon=4, rng=np.random.default_rng(1), gamma=1.0)
    rewards = undiscounted - np.concatenate([undiscounted[..., 1:], np.zeros_like(undiscounted[..., :1])], axis=-1)
    expected = sum(0.5**t * rewards[..., t] for t in range(4))
    np.testing.assert_allclose(returns[..., 0], expected, rtol=1e-5, atol=1e-6)
    np.testing.assert_allclose(returns[..., 3], rewards[..., 3], rtol=1e-5, atol=1e-6)


def test_global_generalization_by_hand():
    """One epoch rebuilt by hand: the held-out policies' true values from their start states, the predictions of a
    network trained on the other policies' samples (each with its own parameters), and their Spearman correlation."""
    n, k, h, seed = 40, 3, 10, 0
    (result,) = run_global_generalization(n_policies=n, n_trajectories=k, horizon=h, representations=("rpr",),
                                          epochs=1, batch_size=64, seed=seed)  # fmt: skip
    rng = np.random.default_rng(seed)
    th.manual_seed(seed)
    params = synthesize_policies(n, rng)
    states, returns = collect_returns(params, k, h, rng)
    order = rng.permutation(n)
    train, test = order[:32], order[32:]
    network = _PointWalkerPeVFA(RawPolicyRepresentation(POLICY_LAYOUT), POLICY_LAYOUT.n_params)
    optimizer = th.optim.Adam(network.parameters(), lr=0.005)
    x = th.as_tensor(states[train].reshape(-1, 6))
    p = th.as_tensor(np.repeat(params[train], k * h, axis=0))
    y = th.as_tensor(returns[train].reshape(-1))
    for batch in th.randperm(len(x)).split(64):
        loss = F.mse_loss(network(x[batch], p[batch]), y[batch])
        optimizer.zero_grad()
        loss.backward()
        optimizer.step()
    with th.no_grad():
        predicted = network(th.as_tensor(states[test, :, 0].reshape(-1, 6)), th.as_tensor(np.repeat(params[test], k, axis=0)))
    np.testing.assert_allclose(result.true_test_values, returns[test, :, 0].mean(axis=1), rtol=1e-6)
    np.testing.assert_allclose(result.predicted_test_values, predicted.reshape(8, k).mean(dim=1).numpy(), rtol=1e-4, atol=1e-5)
    from scipy.stats import spearmanr

    assert result.spearman == pytest.approx(spearmanr(result.true_test_values, result.predicted_test_values).statistic)


def test_zero_shot_and_embedding_maps_restore_the_training_mode():
    """Both diagnostics read the policy in evaluation mode and leave it in the mode they found it in."""
    model = PPOPeVFA("MlpPolicy", "CartPole-v1", **FAST).learn(192)
    obs = np.zeros((2, 4), np.float32)
    for training in (False, True):
        model.policy.set_training_mode(training)
        predict_policy_values(model, model, obs)
        assert model.policy.training is training
        policy_embeddings(model)
        assert model.policy.training is training


def test_zero_shot_probe_of_an_empty_history_cycles_the_given_observations(monkeypatch):
    """Without a history, SPR's probe states cycle through the given observations."""
    model = PPOPeVFA("MlpPolicy", "Pendulum-v1", representation="spr", **FAST)
    probes, record_policy = [], zero_shot.record_policy
    monkeypatch.setattr(
        zero_shot, "record_policy", lambda pol, lay, probe, code: probes.append(probe) or record_policy(pol, lay, probe, code)
    )
    obs = np.arange(15, dtype=np.float32).reshape(5, 3)
    predict_policy_values(model, model, obs)
    n_pairs = model.policy.n_recorded_pairs
    assert n_pairs > 5
    np.testing.assert_array_equal(probes[0], obs[np.arange(n_pairs) % 5])


def test_embedding_map_colours_and_minimum(tmp_path, monkeypatch):
    """One panel coloured by each policy's episode return, the other by its id; fewer than 3 policies refused."""
    with pytest.raises(ValueError, match="at least 3"):
        policy_embeddings(PPOPeVFA("MlpPolicy", "CartPole-v1", **FAST).learn(64))
    model = PPOPeVFA("MlpPolicy", "CartPole-v1", **FAST).learn(640)
    ids = np.array(model.history.policy_ids)
    returns = np.array([model.history.record_info(int(i)).get("episode_return", np.nan) for i in ids], dtype=float)
    figures, save = [], embedding_maps.save_figure
    monkeypatch.setattr(embedding_maps, "save_figure", lambda fig, png: figures.append(fig) or save(fig, png))
    embedding_maps.plot_embedding_maps(model, tmp_path / "m.png", methods=("pca",))
    by_return, by_id = figures[0].axes[0], figures[0].axes[1]
    known = np.isfinite(returns)
    np.testing.assert_allclose(by_return.collections[0].get_array(), returns[known])
    np.testing.assert_array_equal(by_id.collections[0].get_array(), ids)


def _go_on(callback_class, model_class, env: str, first: int, then: int, split: bool, **kwargs):
    """A run of ``first`` then ``then`` steps with the diagnostic: the same callback, or (``split``) a new one loaded
    with its ``state_dict`` between the two learn calls."""
    model = model_class("MlpPolicy", env, **{"seed": 0, **kwargs})
    callback = callback_class()
    model.learn(first, callback=callback)
    if split:
        state = callback.state_dict()
        callback.results.append({"not": "saved"})  # the state is a copy: what the callback does next is not in it
        for parameter in callback.critic.parameters():
            parameter.data.add_(1.0)
        callback = callback_class()
        callback.load_state_dict(state)
    model.learn(then, callback=callback, reset_num_timesteps=False)
    return callback


@pytest.mark.parametrize("kind", ["v", "q"])
def test_a_diagnostic_goes_on_from_its_state_as_if_never_stopped(kind):
    """A new callback loaded with another's state carries on its conventional critic, optimizer and results, and
    draws no random numbers doing it: the run goes on as with the same callback, to the bit."""
    from sb3_pevfa import TD3PeVFA
    from sb3_pevfa.diagnostics import QLocalGeneralizationCallback

    if kind == "v":
        runs = [_go_on(LocalGeneralizationCallback, PPOPeVFA, "CartPole-v1", 192, 128, split, **FAST) for split in (0, 1)]
    else:
        options = dict(snapshot_freq=100, gamma=0.9, learning_starts=100, batch_size=32, policy_kwargs=dict(net_arch=[32]))
        runs = [_go_on(QLocalGeneralizationCallback, TD3PeVFA, "Pendulum-v1", 450, 450, split, **options)
                for split in (0, 1)]  # fmt: skip
    same, loaded = runs
    assert len(same.results) > 3 and loaded.results == same.results
    for name in loaded.saved_attributes[:-1]:  # the critics (the optimizers' states follow from them)
        for ours, theirs in zip(getattr(loaded, name).state_dict().values(), getattr(same, name).state_dict().values()):
            assert th.equal(ours, theirs)


def test_a_diagnostic_state_is_checked():
    callback = LocalGeneralizationCallback()
    with pytest.raises(RuntimeError, match="no state before its first learn"):
        callback.state_dict()
    with pytest.raises(ValueError, match="needs optimizer, results; got critic"):
        callback.load_state_dict({"critic": {}})
    model = PPOPeVFA("MlpPolicy", "CartPole-v1", **FAST)
    model.learn(64, callback=callback)
    wider = LocalGeneralizationCallback(net_arch=(32,))
    wider.load_state_dict(callback.state_dict())
    with pytest.raises(RuntimeError, match="size mismatch"):  # torch's: the critic is not the one saved
        model.learn(64, callback=wider, reset_num_timesteps=False)


def _tensors(tree):
    if isinstance(tree, th.Tensor):
        yield tree
    elif isinstance(tree, dict | list | tuple):
        for value in tree.values() if isinstance(tree, dict) else tree:
            yield from _tensors(value)


def test_a_loaded_state_goes_to_the_next_learn_of_any_model_and_stays_as_given(tmp_path):
    """A callback that has a critic, loaded with a state, then learning with the same model or another one (loaded
    from a file): the state's critic goes on; training changes the callback's copies, not the state given."""
    model = PPOPeVFA("MlpPolicy", "CartPole-v1", **FAST)
    callback = LocalGeneralizationCallback()
    model.learn(128, callback=callback)
    state = callback.state_dict()
    given = [tensor.clone() for tensor in _tensors(state)]
    model.learn(64, callback=callback, reset_num_timesteps=False)  # the callback moves on from the state
    callback.load_state_dict(state)  # back to it, with the same model
    model.learn(0, callback=callback, reset_num_timesteps=False)
    assert all(th.equal(callback.critic.state_dict()[key], value) for key, value in state["critic"].items())
    model.learn(64, callback=callback, reset_num_timesteps=False)
    model.save(tmp_path / "model")
    model.save_history(tmp_path / "history")
    loaded = PPOPeVFA.load(tmp_path / "model", env=model.get_env())
    loaded.load_history(tmp_path / "history")
    callback.load_state_dict(state)
    assert len(callback.results) == 2 and callback.state_dict()["results"] == state["results"]
    loaded.learn(0, callback=callback, reset_num_timesteps=False)
    assert all(th.equal(callback.critic.state_dict()[key], value) for key, value in state["critic"].items())
    loaded.learn(128, callback=callback, reset_num_timesteps=False)
    assert len(callback.results) == 4 and callback.optimizer.state_dict()["state"][0]["step"] > 2
    assert all(th.equal(now, before) for now, before in zip(_tensors(state), given, strict=True))
