"""The local-generalization diagnostic of the off-policy PeVFAs (a conventional twin critic beside the run)."""

import copy
import warnings

import numpy as np
import pytest
import torch as th
from conftest import DictPendulum, read_progress
from stable_baselines3 import SAC, TD3
from stable_baselines3.common.env_util import make_vec_env
from stable_baselines3.common.logger import configure
from stable_baselines3.common.utils import obs_as_tensor

from sb3_pevfa import PolicyRecord, SACPeVFA, TD3PeVFA
from sb3_pevfa.diagnostics.local_generalization import ERROR_KEYS
from sb3_pevfa.diagnostics.q_local_generalization import QLocalGeneralizationCallback, soft_monte_carlo_returns


def tiny(**kwargs) -> dict:
    return dict(learning_starts=100, batch_size=32, policy_kwargs=dict(net_arch=[32, 32]), seed=0, **kwargs)


def test_soft_monte_carlo_returns_by_hand():
    g = 0.5
    rewards = np.array([[1.0, 2.0], [3.0, 4.0], [5.0, 6.0], [7.0, 8.0], [9.0, 10.0]])
    bonuses = np.array([[0.1, 0.2], [0.3, 0.4], [0.5, 0.6], [0.7, 0.8], [0.9, 1.0]])
    # env 0: an episode terminates at row 2, the next is open; env 1: an episode is truncated at row 3, the next open
    ends = np.array([[0, 0], [0, 0], [1, 0], [0, 1], [0, 0]], dtype=bool)
    terminal = np.array([[0, 0], [0, 0], [1, 0], [0, 0], [0, 0]], dtype=bool)
    returns, missing = soft_monte_carlo_returns(rewards, ends, terminal, bonuses, g)
    g2 = 5.0
    g1 = 3.0 + g * (g2 - 0.5)
    g0 = 1.0 + g * (g1 - 0.3)
    g4 = 9.0
    g3 = 7.0 + g * (g4 - 0.9)
    np.testing.assert_allclose(returns[:, 0], [g0, g1, g2, g3, g4])
    np.testing.assert_allclose(missing[:, 0], [0, 0, 0, g**2, g])
    h3 = 8.0
    h2 = 6.0 + g * (h3 - 0.8)
    h1 = 4.0 + g * (h2 - 0.6)
    h0 = 2.0 + g * (h1 - 0.4)
    np.testing.assert_allclose(returns[:, 1], [h0, h1, h2, h3, 10.0])
    np.testing.assert_allclose(missing[:, 1], [g**4, g**3, g**2, g, g])


def _twin(sb3_class, model, callback, **kwargs):
    """SB3's algorithm holding the callback's conventional critic, the model's actor and replay buffer."""
    twin = sb3_class("MlpPolicy", "Pendulum-v1", **kwargs, **tiny())
    twin.critic.load_state_dict(callback.critic.state_dict())
    twin.critic_target.load_state_dict(callback.critic_target.state_dict())
    twin.critic.optimizer.load_state_dict(copy.deepcopy(callback.optimizer.state_dict()))  # torch shares tensors
    twin.actor.load_state_dict(model.actor.state_dict())
    twin.replay_buffer = model.replay_buffer
    twin.set_logger(configure(None, []))
    model.replay_buffer.dones[:60:3] = 1.0  # some terminal transitions (Pendulum has none)
    return twin


def _assert_same_critics(twin, callback) -> None:
    for ours, theirs in ((callback.critic, twin.critic), (callback.critic_target, twin.critic_target)):
        for name, value in theirs.state_dict().items():
            th.testing.assert_close(ours.state_dict()[name], value, atol=1e-7, rtol=0)


def test_the_conventional_critic_updates_as_sb3_td3_updates_its_critic():
    model = TD3PeVFA("MlpPolicy", "Pendulum-v1", policy_delay=1, **tiny())
    callback = QLocalGeneralizationCallback()
    model.learn(150, callback=callback)
    twin = _twin(TD3, model, callback, policy_delay=1)  # its critic, then its actor and both targets
    twin.actor_target.load_state_dict(model.actor_target.state_dict())
    before = {k: v.clone() for k, v in callback.critic_target.state_dict().items()}
    np.random.seed(3)
    th.manual_seed(3)
    twin.train(1, model.batch_size)
    np.random.seed(3)
    th.manual_seed(3)
    callback._train_critic(polyak=True)
    _assert_same_critics(twin, callback)
    assert any(not th.equal(before[k], v) for k, v in callback.critic_target.state_dict().items())


def test_the_conventional_critic_updates_as_sb3_sac_updates_its_critic():
    model = SACPeVFA("MlpPolicy", "Pendulum-v1", **tiny())
    callback = QLocalGeneralizationCallback()
    model.learn(150, callback=callback)
    twin = _twin(SAC, model, callback)
    twin.log_ent_coef.data.copy_(model.log_ent_coef.data)  # alpha before its update, as SAC's target reads it
    np.random.seed(3)
    th.manual_seed(3)
    twin.train(1, model.batch_size)
    np.random.seed(3)
    th.manual_seed(3)
    th.randn(model.batch_size, 1)  # SAC's update draws the actor's actions at the states first
    callback._train_critic(polyak=True)
    _assert_same_critics(twin, callback)
    model.lr_schedule, model._current_progress_remaining = (lambda progress: 1e-3 * progress), 0.5
    callback._train_critic(polyak=False)
    assert callback.optimizer.param_groups[0]["lr"] == pytest.approx(5e-4)  # at the model's learning rate, as SB3's


@pytest.mark.parametrize(
    ("pevfa_class", "expected"), [(TD3PeVFA, [False, True, False, False]), (SACPeVFA, [True, False, False, True])]
)
def test_the_conventional_target_moves_on_sb3s_schedule(pevfa_class, expected):
    delay = dict(policy_delay=3) if pevfa_class is TD3PeVFA else dict(target_update_interval=3)
    model = pevfa_class("MlpPolicy", "Pendulum-v1", **delay, **tiny())
    callback = QLocalGeneralizationCallback()
    model.learn(110, callback=callback)
    polyaks = []
    callback._train_critic = polyaks.append  # the flags of the updates owed to the model's
    callback._updates, model._n_updates = 4, 8  # TD3: its updates 5-8 (every 3rd); SAC: one train call's 4 steps
    callback._catch_up()
    assert polyaks == expected and callback._updates == 8


@pytest.mark.parametrize(("normalized", "dict_obs"), [(False, False), (True, False), (True, True)])
def test_before_is_the_frozen_critics_and_after_the_live_ones_with_the_window_snapshot(normalized, dict_obs):
    from stable_baselines3.common.env_util import make_vec_env
    from stable_baselines3.common.vec_env import VecNormalize

    env = make_vec_env(DictPendulum if dict_obs else "Pendulum-v1", seed=0)
    env = VecNormalize(env) if normalized else env
    model = SACPeVFA("MultiInputPolicy" if dict_obs else "MlpPolicy", env, snapshot_freq=50, gamma=0.9, **tiny())
    callback = QLocalGeneralizationCallback()
    model.learn(300, callback=callback)
    policy_id, critic = model.history.latest_policy_id, model.policy.critic
    callback._open_window(policy_id)
    frozen = copy.deepcopy(critic.state_dict())
    callback._window["start"] = model.replay_buffer.pos - 100  # the last 100 transitions as the window's
    callback._window["first_row"] -= 100
    with th.no_grad():  # the live actor, critics and encoder move, and a new snapshot is recorded, after the window opened
        generator = th.Generator().manual_seed(0)
        for parameter in model.actor.parameters():  # both errors read the window's snapshot, not the live actor
            parameter.add_(0.5 * th.randn(parameter.shape, generator=generator))
        for q_net in critic.q_networks:
            q_net.head.output.bias += 1.0
        critic.representation.projection.bias += 0.5
        for q_net in callback.critic.q_networks:
            q_net[-1].bias += 2.0
    model.record_snapshot()
    callback._close_window()
    closed = callback._closed
    rows = (model.replay_buffer.pos - 100 + np.arange(100)) % model.replay_buffer.buffer_size
    stored = model.replay_buffer.observations  # as the env gave them, unnormalized
    observations = {key: value[rows, 0] for key, value in stored.items()} if dict_obs else stored[rows, 0]
    observations = env.normalize_obs(observations) if normalized else observations  # as the critics read them
    observations = obs_as_tensor(observations, th.device("cpu"))
    actions = th.as_tensor(model.replay_buffer.actions[rows, 0])
    record = PolicyRecord.from_numpy(model.history.records([policy_id]))

    def q_min(state_dict) -> np.ndarray:
        copied = copy.deepcopy(critic)
        copied.load_state_dict(state_dict)
        copied.train(False)
        with th.no_grad():
            return th.min(th.cat(copied(observations, actions, copied.representation(record)), dim=1), dim=1)[0].numpy()

    np.testing.assert_allclose(closed["pevfa_before"], q_min(frozen), atol=1e-6)
    np.testing.assert_allclose(closed["pevfa_after"], q_min(critic.state_dict()), atol=1e-6)
    np.testing.assert_allclose(closed["vfa_after"], closed["vfa_before"] + 2.0, atol=1e-5)
    assert closed["policy_id"] == policy_id


@pytest.mark.parametrize("normalized", [False, True])
def test_a_window_is_scored_on_the_transitions_whose_return_is_complete_enough(normalized):
    from stable_baselines3.common.vec_env import VecNormalize

    env = VecNormalize(make_vec_env("Pendulum-v1", seed=0)) if normalized else "Pendulum-v1"
    model = SACPeVFA("MlpPolicy", env, gamma=0.9, **tiny())
    callback = QLocalGeneralizationCallback(tail_weight=0.01)
    model.learn(400, callback=callback)  # 200-step episodes: truncated at rows 199 and 399
    closed = {"start": 340, "first_row": callback._rows_added - 60, "policy_id": 0, "n_rows": 50, "timesteps": 400}
    closed.update({key: np.zeros(50) for key in ERROR_KEYS})  # predictions of 0: the error is the mean squared return
    callback._score(closed)
    buffer, rows = model.replay_buffer, np.arange(340, 400)
    rewards = env.normalize_reward(buffer.rewards[rows]) if normalized else buffer.rewards[rows]  # as the critics learn
    returns, _ = soft_monte_carlo_returns(rewards, buffer.dones[rows], np.zeros((60, 1), bool), callback.bonuses[rows], 0.9)
    result = callback.results[-1]
    assert result["n_states"] == 17  # rows 340-356: at least 44 steps before the cut (0.9^44 < 0.01 < 0.9^43)
    np.testing.assert_allclose(result["pevfa_before"], np.mean(returns[:17, 0] ** 2), rtol=1e-6)


def test_a_tail_weight_of_0_scores_the_transitions_whose_episode_terminated():
    model = TD3PeVFA("MlpPolicy", "Pendulum-v1", **tiny())
    callback = QLocalGeneralizationCallback(tail_weight=0.0)
    model.learn(110, callback=callback)
    buffer, rows = model.replay_buffer, np.arange(40, 100)
    buffer.dones[[60, 80]], buffer.timeouts[[60, 80]] = 1.0, [[0.0], [1.0]]  # terminated at row 60, truncated at 80
    closed = {"start": 40, "first_row": callback._rows_added - 60, "policy_id": 0, "n_rows": 50, "timesteps": 110}
    closed.update({key: np.zeros(50) for key in ERROR_KEYS})
    callback._score(closed)
    terminal = buffer.dones[rows] * (1 - buffer.timeouts[rows])
    returns, _ = soft_monte_carlo_returns(buffer.rewards[rows], buffer.dones[rows], terminal, np.zeros((60, 1)), 0.99)
    result = callback.results[-1]
    assert result["n_states"] == 21  # rows 40-60, whose returns miss nothing
    np.testing.assert_allclose(result["pevfa_before"], np.mean(returns[:21, 0] ** 2), rtol=1e-6)


def test_a_window_is_scored_while_the_replay_buffer_holds_all_its_transitions():
    model = TD3PeVFA("MlpPolicy", "Pendulum-v1", buffer_size=100, **tiny())
    callback = QLocalGeneralizationCallback()
    model.learn(110, callback=callback)
    results = callback.results

    def closed(count: int) -> dict:  # a window of the latest ``count`` transitions
        window = {"start": (model.replay_buffer.pos - count) % 100, "first_row": callback._rows_added - count}
        return {**window, "policy_id": 0, "n_rows": 50, "timesteps": 110, **{key: np.zeros(50) for key in ERROR_KEYS}}

    scored = len(results)
    callback._score(closed(100))  # the whole buffer
    assert len(results) == scored + 1
    with pytest.warns(UserWarning, match=r"The replay buffer \(100 rows\) overwrote transitions of a window"):
        callback._score(closed(101))  # its first transition overwritten
    assert len(results) == scored + 1


def test_the_entropy_bonus_of_each_replay_row_is_its_actions():
    env = make_vec_env("Pendulum-v1", n_envs=2, seed=0)
    model = SACPeVFA(  # nothing moves: the actor and alpha are those of every step
        "MlpPolicy", env, snapshot_freq=20, learning_rate=0.0, ent_coef=0.5, **tiny()
    )
    callback = QLocalGeneralizationCallback()
    model.learn(400, callback=callback)
    buffer = model.replay_buffer
    rows = np.arange(100, buffer.pos)  # env steps after the first window opened (the first snapshot at step 50)
    observations = th.as_tensor(buffer.observations[rows].reshape(-1, 3))
    with th.no_grad():
        mean, log_std, kwargs = model.actor.get_action_dist_params(observations)
        distribution = model.actor.action_dist.proba_distribution(mean, log_std, **kwargs)
        log_prob = distribution.log_prob(th.as_tensor(buffer.actions[rows].reshape(-1, 1))).numpy()
    np.testing.assert_allclose(callback.bonuses[rows].reshape(-1), 0.5 * log_prob, rtol=1e-5, atol=1e-5)
    assert not callback.bonuses[:50].any()  # no window yet: not needed


def test_a_later_learn_opens_its_first_window_at_its_next_snapshot():
    model = TD3PeVFA("MlpPolicy", "Pendulum-v1", snapshot_freq=100, gamma=0.9, **tiny())
    callback = QLocalGeneralizationCallback()
    model.learn(450, callback=callback)
    latest, scored = model.history.latest_policy_id, len(callback.results)
    model.learn(450, callback=callback, reset_num_timesteps=False)
    assert callback.results[scored]["policy_id"] == latest + 1


@pytest.mark.parametrize("pevfa_class", [SACPeVFA, TD3PeVFA])
def test_a_run_logs_the_four_errors_per_window(tmp_path, pevfa_class):
    model = pevfa_class("MlpPolicy", "Pendulum-v1", snapshot_freq=100, gamma=0.9, **tiny())
    model.set_logger(configure(str(tmp_path), ["csv"]))
    callback = QLocalGeneralizationCallback()
    model.learn(900, callback=callback)
    results = callback.results
    assert len(results) >= 5  # a window per 100 gradient steps (the last ones scored at the end)
    scored = [r for r in results if r["n_states"] > 0]
    assert len(scored) >= 4
    for result in scored:
        assert all(np.isfinite(result[key]) and result[key] > 0 for key in ERROR_KEYS)
    assert any(r["pevfa_before"] != r["pevfa_after"] for r in scored)
    assert any(r["vfa_before"] != r["vfa_after"] for r in scored)
    progress = read_progress(tmp_path)
    logged = [row for row in progress if row.get("pevfa/local_gen/timesteps", "") != ""]
    assert [float(row["pevfa/local_gen/timesteps"]) for row in logged] == [r["timesteps"] for r in results]
    rows = callback.bonuses[:900, 0]
    assert (np.abs(rows) > 0).any() == (pevfa_class is SACPeVFA)  # alpha log pi of SAC's actions, none for TD3


def test_it_needs_an_off_policy_pevfa():
    with pytest.raises(TypeError, match="SACPeVFA or TD3PeVFA"):
        SAC("MlpPolicy", "Pendulum-v1", **tiny()).learn(10, callback=QLocalGeneralizationCallback())
    with pytest.raises(ValueError, match="tail_weight"):
        QLocalGeneralizationCallback(tail_weight=1.0)


def test_windows_without_a_scored_transition_are_said_once():
    """Pendulum's episodes end at a time limit of 200 steps: at gamma 0.99 a return misses more than 1 % of its value
    unless 459 steps follow it, so no transition is ever scored; the callback says so once, and the errors are NaN."""
    model = SACPeVFA("MlpPolicy", "Pendulum-v1", snapshot_freq=100, **tiny())
    callback = QLocalGeneralizationCallback()
    with pytest.warns(UserWarning, match=r"No transition of a window .* went on 459 steps after it") as caught:
        model.learn(600, callback=callback)
    assert sum("No transition of a window" in str(w.message) for w in caught) == 1
    assert callback.results and all(r["n_states"] == 0 and np.isnan(r["pevfa_before"]) for r in callback.results)
    with pytest.warns(UserWarning, match=r"of its discounted value \(its episode terminated\)\. Episodes"):
        model.learn(300, callback=QLocalGeneralizationCallback(tail_weight=0.0))  # only a terminated episode's
    scored = SACPeVFA("MlpPolicy", "Pendulum-v1", snapshot_freq=100, gamma=0.9, **tiny())  # 44 steps suffice
    with warnings.catch_warnings():
        warnings.simplefilter("error", UserWarning)
        scored.learn(600, callback=QLocalGeneralizationCallback())
