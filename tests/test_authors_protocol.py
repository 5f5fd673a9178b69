"""The authors' protocol (sb3_pevfa.protocols.authors_protocol): each mechanic against their code's arithmetic."""

import copy
import inspect
import warnings

import gymnasium as gym
import numpy as np
import pytest
import torch as th
from stable_baselines3.common.env_util import make_vec_env
from torch import nn

from sb3_pevfa import A2CPeVFA, PPOPeVFA
from sb3_pevfa.envs.time_feature import ElapsedTimeFeatureWrapper
from sb3_pevfa.pevfa.episodes import episode_lengths, historical_updates
from sb3_pevfa.protocols import AUTHORS_DEVIATIONS, authors_env, authors_protocol, make_authors_env

#: The authors' protocol at a tiny scale: 5 episodes or 200 steps an iteration, historical updates after 100 steps
TINY = dict(n_steps=200, batch_size=32, history_learning_starts=100, history_buffer_size=5_000)


class Episodes(gym.Env):
    """Episodes of the given lengths in turn (terminated), reward 1 a step, a one-dimensional state and action; the
    first state is 0.5, where a critic with zero biases reads a value other than 0."""

    observation_space = gym.spaces.Box(-np.inf, np.inf, (1,), np.float32)
    action_space = gym.spaces.Box(-1.0, 1.0, (1,), np.float32)

    def __init__(self, lengths=(30,)):
        self.lengths, self.episode, self.t = tuple(lengths), -1, 0

    def reset(self, *, seed=None, options=None):
        super().reset(seed=seed)
        self.episode, self.t = self.episode + 1, 0
        return np.array([0.5], np.float32), {}

    def step(self, action):
        self.t += 1
        length = self.lengths[self.episode % len(self.lengths)]
        return np.array([self.t / 10], np.float32), 1.0, self.t >= length, False, {}


def _model(lengths=(30,), algorithm="ppo_pevfa", max_episode_steps=None, **overrides) -> PPOPeVFA:
    def make():
        env = Episodes(lengths)
        return gym.wrappers.TimeLimit(env, max_episode_steps) if max_episode_steps else env

    env = make_vec_env(make, n_envs=1, seed=0)
    return PPOPeVFA("MlpPolicy", env, **authors_protocol(algorithm, **{**TINY, **overrides}), seed=0)


def _gae_of_episodes(values: np.ndarray, episodes: int, gamma: float, gae_lambda: float) -> np.ndarray:
    """GAE written out for ``episodes`` whole episodes of equal length, one after another, reward 1 a step: V = 0
    after each episode's last step (no bootstrap at its end, truncated or not)."""
    values = values.reshape(episodes, -1)
    next_values = np.concatenate([values[:, 1:], np.zeros((episodes, 1))], axis=1)
    deltas = 1.0 + gamma * next_values - values
    advantages, gae = np.zeros_like(deltas), np.zeros(episodes)
    for t in reversed(range(values.shape[1])):
        gae = deltas[:, t] + gamma * gae_lambda * gae
        advantages[:, t] = gae
    return advantages.reshape(-1)


def _rollout(model: PPOPeVFA) -> None:
    _, callback = model._setup_learn(10_000, reset_num_timesteps=False)
    model.collect_rollouts(model.env, callback, model.rollout_buffer, model.n_steps)


@pytest.mark.parametrize(
    ("lengths", "expected"),
    [
        ((30,), [150, 150]),  # 5 episodes first
        ((70,), [210, 210]),  # 200 steps first: the episode under way is finished (3 x 70)
        ((100,), [200, 200]),  # 2 x 100 = 200 reaches the step count at an episode end
        ((100, 20), [220, 240]),
        ((199, 3), [202, 202]),  # 199 + 3 >= 200 after the second episode
    ],
)
def test_iterations_end_after_five_episodes_or_at_the_episode_end_past_n_steps(lengths, expected):
    model = _model(lengths, algorithm="ppo")
    sizes = []
    for _ in expected:
        _rollout(model)
        sizes.append(model.rollout_buffer.buffer_size)
        assert model.rollout_buffer.full and len(model.rollout_buffer.observations) == sizes[-1]
        assert model._last_episode_starts[0]  # every rollout ends with an episode
    assert sizes == expected and model.num_timesteps == sum(expected)


def _authors_updates(episode_lengths_in_order: list[int], train_freq: int, starts: int) -> list[int]:
    """Their loop (mujoco_run_ppo_pevf_e2e_opr_Sep.py): at each episode's end, once the step counter is past
    ``starts``, ``counter // freq - (counter - episode_steps) // freq`` updates."""
    counter, updates = 0, []
    for length in episode_lengths_in_order:
        counter += length
        updates.append(counter // train_freq - (counter - length) // train_freq if counter > starts else 0)
    return updates


def test_historical_updates_are_counted_per_episode_as_the_authors_count_them():
    lengths = [37, 3, 50, 10, 7, 1000, 9, 11]
    all_updates = _authors_updates(lengths, 10, 100)
    assert all_updates[:5] == [0] * 5 and all_updates[5] == 110 - 10  # none for the episode ending at exactly 100
    # in rollouts of whole episodes, any split of the episodes gives the same counts
    first, second = lengths[:4], lengths[4:]
    np.testing.assert_array_equal(historical_updates(np.array(first), sum(first), 10, 100), [0, 0, 0, 0])
    np.testing.assert_array_equal(historical_updates(np.array(second), sum(lengths), 10, 100), all_updates[4:])
    np.testing.assert_array_equal(
        historical_updates(np.array(lengths), sum(lengths), 10, 99), _authors_updates(lengths, 10, 99)
    )
    starts = np.zeros(len(lengths) and sum(second), bool)
    starts[np.cumsum([0, *second[:-1]])] = True
    np.testing.assert_array_equal(episode_lengths(starts), second)


def test_the_model_runs_that_many_historical_updates_each_iteration():
    # the first iteration (139 steps) ends before the updates start: their memory would still be empty
    model = _model((30, 17, 45), history_learning_starts=150)
    steps, episodes, calls, samples = [], [], [], []
    step, sample = model._critic_step, model.history.sample
    model._critic_step = lambda loss, what: calls.append(what) or step(loss, what)  # type: ignore[method-assign]
    model.history.sample = lambda *a, **k: samples.append((a, k)) or sample(*a, **k)  # type: ignore[method-assign]
    for _ in range(4):
        calls.clear()
        _rollout(model)
        lengths = episode_lengths(model.rollout_buffer.episode_starts)
        episodes.extend(lengths)
        steps.append(model.num_timesteps)
        model.train()
        expected = sum(_authors_updates(episodes, 10, 150)[len(episodes) - len(lengths) :])
        assert calls.count("historical value loss") == expected
    assert sum(_authors_updates(episodes, 10, 150)) > 0
    # each: 64 samples drawn uniformly from the memory, the current policy's left out (its own fit comes first)
    assert len(samples) == sum(_authors_updates(episodes, 10, 150))
    assert all(a == (64,) and k == {"exclude_policy": model.history.latest_policy_id} for a, k in samples[-3:])


def test_the_historical_schedule_and_memory_are_the_authors():
    arguments = authors_protocol("ppo_pevfa")
    assert arguments["history_learning_starts"] == 5_000 and arguments["history_train_freq"] == 10
    assert arguments["history_batch_size"] == 64 and arguments["history_batch_policies"] is None  # uniform samples
    max_policies = inspect.signature(PPOPeVFA).parameters["history_max_policies"].default
    assert arguments["history_buffer_size"] == 200_000 and arguments.get("history_max_policies", max_policies) == 10_000
    assert arguments["rollout_encoder_gradient"] is True and arguments["representation"] == "opr"
    assert authors_protocol("ppo")["history_train_freq"] == 0


def test_monte_carlo_targets_and_gae_end_at_every_episode_end_and_at_the_cap():
    # episodes of 40 steps capped at 25 by a time limit: truncated, not bootstrapped
    model = _model((40,), algorithm="ppo", max_episode_steps=25, gamma=0.9, gae_lambda=0.8)
    _rollout(model)
    buffer, gamma = model.rollout_buffer, 0.9
    # the state after the rollout's last step has a value: a bootstrap from it would show in every number below
    assert abs(model.policy.predict_values(model.policy.obs_to_tensor(model._last_obs)[0]).item()) > 0.1
    assert buffer.buffer_size == 125 and np.all(buffer.rewards == 1.0)  # no bootstrap added to the rewards
    mc = np.array([(1 - gamma ** (25 - t)) / (1 - gamma) for t in range(25)] * 5, np.float32)
    np.testing.assert_allclose(buffer.returns[:, 0], mc, rtol=1e-5)
    model._recompute_advantages()  # the critic-first order's GAE, from the same critic
    expected = _gae_of_episodes(buffer.values[:, 0], episodes=5, gamma=gamma, gae_lambda=0.8)
    np.testing.assert_allclose(buffer.advantages[:, 0], expected, rtol=1e-4, atol=1e-5)


def test_the_actor_update_is_ten_full_batch_adam_steps():
    model = _model((150, 90), algorithm="ppo")
    _rollout(model)  # whole episodes past n_steps = 200: one batch of 240, not n_steps
    buffer = model.rollout_buffer
    assert buffer.buffer_size == 240
    observations = th.as_tensor(buffer.observations[:, 0])
    actions = th.as_tensor(buffer.actions[:, 0])
    old_log_prob = th.as_tensor(buffer.log_probs[:, 0])
    advantages = th.as_tensor(buffer.advantages[:, 0])
    # by hand: advantages normalized over the whole batch, the clipped surrogate, 10 Adam steps on all of it
    policy = copy.deepcopy(model.policy)
    actor = [p for p in policy.optimizer.param_groups[0]["params"]]
    optimizer = th.optim.Adam([{"params": actor, "lr": 1e-4}, {"params": [policy.log_std], "lr": 6.5e-4}], eps=1e-8)
    normalized = (advantages - advantages.mean()) / (advantages.std() + 1e-8)
    for _ in range(10):
        log_prob = policy.get_distribution(observations).log_prob(actions)
        ratio = th.exp(log_prob - old_log_prob)
        loss = -th.min(normalized * ratio, normalized * th.clamp(ratio, 0.8, 1.2)).mean()
        optimizer.zero_grad()
        loss.backward()
        optimizer.step()
    # no clipping, no entropy bonus: asserted directly (here SB3's 0.5 clip would not act, a 0.01 bonus hides in 1e-6)
    assert model.max_grad_norm == float("inf") and model.ent_coef == 0.0
    steps = []
    step = model.policy.optimizer.step
    model.policy.optimizer.step = lambda *a, **k: steps.append(1) or step(*a, **k)  # type: ignore[method-assign]
    with model.policy.critic_frozen():
        model._train_actor_critic()
    assert len(steps) == 10 and model._n_updates == 10  # 10 epochs of one batch: 10 Adam steps
    assert model.batch_size == 32  # the critic's minibatch size is back
    for ours, theirs in zip(model.policy.layout.flatten(model.policy), policy.layout.flatten(policy)):
        assert abs(float(ours) - float(theirs)) <= 1e-6
    assert not th.equal(model.policy.layout.flatten(model.policy), model.policy.layout.flatten(_model((30,), "ppo").policy))


def test_the_log_variance_of_13_rows_is_one_log_std_at_6_5_times_the_rate():
    model = _model(algorithm="ppo")
    policy = model.policy
    group = next(g for g in policy.optimizer.param_groups if g.get("name") == "log_std")
    assert group["params"] == [policy.log_std] and group["lr"] == pytest.approx(6.5e-4)
    rows = th.zeros(13, 1, requires_grad=True)  # theirs: log-var = sum of the rows - 1, Adam at the actor's rate
    theirs = th.optim.Adam([rows], lr=1e-4, eps=1e-8)
    generator = th.Generator().manual_seed(0)
    for _ in range(200):
        actions, mean = th.randn(64, 1, generator=generator) * 2, th.randn(64, 1, generator=generator)
        for log_std, optimizer in ((policy.log_std, policy.optimizer), ((rows.sum(0) - 1) / 2, theirs)):
            loss = -th.distributions.Normal(mean, log_std.exp()).log_prob(actions).mean()
            optimizer.zero_grad()
            loss.backward()
            optimizer.step()
        assert abs(policy.log_std.item() - ((rows.sum() - 1) / 2).item()) < 1e-6
    assert policy.log_std.item() > -0.5 + 0.05  # it moved


def test_weights_are_normal_with_variance_one_over_fan_in_and_biases_zero():
    model = _model(policy_kwargs=dict(net_arch=dict(pi=[400, 400], vf=[400])))
    linears = [m for m in model.policy.modules() if isinstance(m, nn.Linear)]
    assert len(linears) > 8  # actor, critic streams and head, the OPR encoder's row MLPs
    standardized = []
    for layer in linears:
        assert th.all(layer.bias == 0)
        z = layer.weight.detach().flatten() * layer.in_features**0.5  # N(0, 1) if the weights are N(0, 1 / fan_in)
        n = z.numel()
        assert abs(z.std().item() - 1) < 4 / (2 * n) ** 0.5 and abs(z.mean().item()) < 4 / n**0.5, layer
        standardized.append(z)
    z = th.cat(standardized)
    kurtosis = ((z - z.mean()) ** 4).mean() / z.var(unbiased=False) ** 2
    assert abs(kurtosis.item() - 3) < 0.1  # a normal's (a uniform of the same variance: 1.8)
    assert th.all(model.policy.log_std == -0.5)


def test_the_mean_is_tanh_activated_and_the_buffer_keeps_the_clipped_actions():
    model = _model((30,), algorithm="ppo")
    policy = model.policy
    observations = th.linspace(-50, 50, 11).reshape(-1, 1)
    mean = policy.get_distribution(observations).distribution.mean
    latent = policy.mlp_extractor.forward_actor(observations)
    np.testing.assert_allclose(mean.detach(), th.tanh(policy.action_net(latent)).detach(), atol=1e-7)
    params = policy.layout.flatten(policy)[None]
    np.testing.assert_allclose(policy.layout.evaluate(params, observations)[1][0].detach(), mean.detach(), atol=1e-6)
    _rollout(model)
    actions = model.rollout_buffer.actions
    assert actions.min() >= -1.0 and actions.max() <= 1.0 and np.any(np.abs(actions) == 1.0)
    log_probs = policy.get_distribution(th.as_tensor(model.rollout_buffer.observations[:, 0])).log_prob(
        th.as_tensor(actions[:, 0])
    )
    np.testing.assert_allclose(model.rollout_buffer.log_probs[:, 0], log_probs.detach(), atol=1e-5)


def test_the_critic_takes_even_minibatches_the_remainder_left_out():
    counts = {}
    for rule in ("even", "sb3"):
        model = _model((30,), algorithm="ppo", critic_minibatches=rule, history_train_freq=0)
        sizes = []
        step = model._critic_step
        model._critic_step = lambda loss, what, sizes=sizes, step=step: sizes.append(what) or step(loss, what)  # type: ignore
        _rollout(model)  # 150 samples: the authors' one batch of 150; SB3's 32 x 4 and 22
        model._train_critic_on_rollout()
        counts[rule] = len(sizes)
    assert counts == {"even": 10 * 4, "sb3": 10 * 5}
    model = _model((30,), algorithm="ppo", batch_size=128, critic_minibatches="even")
    captured = []
    predict = model.policy.predict_values
    model.policy.predict_values = lambda obs, *a: captured.append(len(obs)) or predict(obs, *a)  # type: ignore
    _rollout(model)
    captured.clear()
    model._train_critic_on_rollout()
    assert captured == [150] * 10  # 150 // (150 // 128) = 150


def test_the_time_feature_is_the_elapsed_fraction_and_episodes_end_at_1000_steps():
    env = authors_env("Pendulum-v1")  # 200 steps of its own: the authors' cap of 1000 replaces it
    observation, _ = env.reset(seed=0)
    assert observation[-1] == 0.0 and env.observation_space.shape == (4,)
    for t in range(1, 1001):
        observation, _, terminated, truncated, _ = env.step(env.action_space.sample())
        assert observation[-1] == pytest.approx(t / 1000) and truncated == (t == 1000) and not terminated
    wrapped = ElapsedTimeFeatureWrapper(gym.make("Pendulum-v1"), test_mode=True)
    assert wrapped.reset(seed=0)[0][-1] == 0.0 and wrapped.step(wrapped.action_space.sample())[0][-1] == 0.0
    # actions in [-1, 1] scaled to the bounds (Pendulum's torque: [-2, 2])
    assert np.all(env.action_space.high == 1.0) and make_authors_env("Pendulum-v1", seed=0).num_envs == 1


def test_authors_protocol_builds_their_networks_and_keeps_them_through_save_and_load(tmp_path):
    model = _model((30,))
    assert model.rollout_episodes == 5 and model.actor_batch_size == "full" and model.critic_minibatches == "even"
    assert model.bootstrap_truncated is False and model.train_on_clipped_actions is True
    assert model.policy.mean_activation_fn is nn.Tanh and model.policy.weight_init == "normal_fan_in"
    assert model.policy.optimizer.defaults["eps"] == 1e-8
    model.learn(400)
    model.save(tmp_path / "model")
    model.save_history(tmp_path / "history")
    loaded = PPOPeVFA.load(tmp_path / "model", env=model.env)
    loaded.load_history(tmp_path / "history")
    assert loaded.policy.weight_init == "normal_fan_in" and loaded.policy.optimizer.defaults["eps"] == 1e-8
    for name in (
        "rollout_episodes",
        "actor_batch_size",
        "critic_minibatches",
        "bootstrap_truncated",
        "train_on_clipped_actions",
    ):
        assert getattr(loaded, name) == getattr(model, name)
    assert loaded.policy.mean_activation_fn is nn.Tanh and loaded.policy.log_std_lr_scale == 6.5
    assert th.equal(loaded.policy.layout.flatten(loaded.policy), model.policy.layout.flatten(model.policy))
    loaded.learn(200, reset_num_timesteps=False)  # trains on: the log-std's rate follows the actor's, scaled
    rates = {g.get("name"): g["lr"] for g in loaded.policy.optimizer.param_groups}
    assert rates == {"actor": 1e-4, "critic": 1e-3, "log_std": pytest.approx(6.5e-4)}
    assert loaded.rollout_buffer.buffer_size < 200 or loaded._last_episode_starts[0]  # whole episodes still
    assert any("log-std" in line for line in AUTHORS_DEVIATIONS)
    # a history of tanh-mean actors does not load into a model of linear means
    linear = PPOPeVFA("MlpPolicy", model.env, **authors_protocol("ppo_pevfa", policy_kwargs=dict(mean_activation_fn=None)))
    with pytest.raises(ValueError, match="actor_mean_activation: file has 'Tanh', model expects None"):
        linear.load_history(tmp_path / "history")


@pytest.mark.parametrize(
    ("kwargs", "message"),
    [
        (dict(rollout_episodes=0), "rollout_episodes must be None"),
        (dict(rollout_episodes=5, fast_path=False), "set fast_path=True"),
        (dict(bootstrap_truncated=False, fast_path=False), "set fast_path=True"),
        (dict(critic_minibatches="odd"), "valid choices: ('sb3', 'even')"),
        (dict(actor_batch_size="all", update_order="critic_first"), "actor_batch_size must be"),
        (dict(actor_batch_size="full"), "update_order='critic_first'"),
        (dict(critic_minibatches="even"), "critic_minibatches='even' shapes the critic's own epochs"),
        (dict(rollout_episodes=5, history_targets="recomputed"), "does not take rollout_episodes"),
        (dict(train_on_clipped_actions=True, use_sde=True, policy_kwargs=dict(squash_output=True)), "not with squash_output"),
        (dict(policy_kwargs=dict(weight_init="xavier", ortho_init=False)), "valid choices: (None, 'normal_fan_in')"),
        (dict(policy_kwargs=dict(weight_init="normal_fan_in")), "pass ortho_init=False"),
        (dict(policy_kwargs=dict(log_std_lr_scale=0.0)), "log_std_lr_scale must be"),
    ],
)
def test_bad_options_are_refused_at_construction(kwargs, message):
    with pytest.raises(ValueError, match=message.replace("(", r"\(").replace(")", r"\)").replace("'", "'")):
        PPOPeVFA("MlpPolicy", "Pendulum-v1", **kwargs)


def test_options_that_need_one_env_or_a_box_say_so():
    with pytest.raises(ValueError, match="n_envs=2"):
        PPOPeVFA("MlpPolicy", make_vec_env("Pendulum-v1", n_envs=2), rollout_episodes=5)
    with pytest.raises(ValueError, match="needs a Box action space"):
        A2CPeVFA("MlpPolicy", "CartPole-v1", train_on_clipped_actions=True)
    with pytest.raises(ValueError, match="mean_activation_fn needs a Box"):
        PPOPeVFA("MlpPolicy", "CartPole-v1", policy_kwargs=dict(mean_activation_fn=nn.Tanh))
    with pytest.raises(ValueError, match="Unknown algorithm 'sac' of the authors' protocol"):
        authors_protocol("sac")


def test_the_key_encoder_of_cl_starts_as_the_encoder_under_their_initialization():
    model = _model(representation_objectives=("cl",))
    encoder, key = model.policy.representation, model.policy.objectives["cl"].key_encoder
    for (name, ours), (_, theirs) in zip(encoder.state_dict().items(), key.state_dict().items(), strict=True):
        assert th.equal(ours, theirs), name


def test_objectives_follow_the_steps_a_rollout_of_whole_episodes_collected():
    model = _model((30,), representation_objectives=("cl",), history_learning_starts=0)
    objective = model.policy.objectives["cl"]
    objective.learning_starts = 0
    calls = []
    loss = objective.loss
    objective.loss = lambda *a, **k: calls.append(1) or loss(*a, **k)  # type: ignore[method-assign]
    for _ in range(3):
        _rollout(model)
        model.train()
    # 15 per 150-step rollout (one per 10 steps), none in the first (a contrast needs two policies); 200 per rollout
    # if each counted n_steps (2000)
    assert model.rollout_buffer.buffer_size == 150 and len(calls) == 0 + 15 + 15


def test_whole_episodes_with_dict_observations_vecnormalize_and_a2c():
    from conftest import DictPendulum
    from stable_baselines3.common.vec_env import VecNormalize

    # Dict observations: Pendulum's 200-step episodes, 2 of them (the second ends past n_steps=300)
    model = PPOPeVFA("MultiInputPolicy", make_vec_env(DictPendulum, n_envs=1, seed=0), rollout_episodes=2, n_steps=300,
                     batch_size=100, n_epochs=1, history_learning_starts=0, seed=0)  # fmt: skip
    model.learn(600)
    buffer = model.rollout_buffer
    assert model.num_timesteps == 800 and buffer.buffer_size == 400
    assert {len(v) for v in buffer.observations.values()} == {400} and model.history.n_samples == 800
    # VecNormalize: the history keeps each rollout's raw observations, all of them
    env = VecNormalize(make_vec_env("Pendulum-v1", n_envs=1, seed=0))
    model = PPOPeVFA("MlpPolicy", env, rollout_episodes=1, n_steps=100, batch_size=100, n_epochs=1, seed=0)
    model.learn(400)
    assert model.history.renormalize and model.history.n_samples == 400 and model.rollout_buffer.buffer_size == 200
    raw = model.history.samples(raw=True)[0]
    assert raw.shape == (400, 3) and np.all(np.abs(raw[:, :2]) <= 1.0)  # cos and sin as the env gave them
    # A2C: one update on each whole episode (200 samples), its critic batch the whole rollout
    model = A2CPeVFA("MlpPolicy", "Pendulum-v1", rollout_episodes=1, n_steps=5, update_order="critic_first", seed=0)
    sizes = []
    step = model._critic_step
    model._critic_step = lambda loss, what: sizes.append(what) or step(loss, what)  # type: ignore[method-assign]
    model.learn(600)
    assert model._n_updates == 3 and model.rollout_buffer.buffer_size == 200
    assert sizes.count("value loss of the critic-first epochs") == 3  # one step on all 200 samples per update


def test_an_actor_minibatch_of_its_own_size():
    model = _model((30,), algorithm="ppo", actor_batch_size=50)
    _rollout(model)  # 150 samples: 3 minibatches of 50 per epoch
    steps = []
    step = model.policy.optimizer.step
    model.policy.optimizer.step = lambda *a, **k: steps.append(1) or step(*a, **k)  # type: ignore[method-assign]
    with model.policy.critic_frozen():
        model._train_actor_critic()
    assert len(steps) == 10 * 3


def test_embedding_diagnostics_are_logged_with_each_row_and_only_then():
    from stable_baselines3.common.logger import KVWriter, Logger

    from sb3_pevfa.pevfa.algorithm import PeVFAAlgorithm

    rows = []

    class Rows(KVWriter):
        def write(self, values, *args, **kwargs):
            rows.append(dict(values))

        def close(self):
            pass

    model = _model((30,), n_steps=100, history_learning_starts=0)
    model.set_logger(Logger(folder=None, output_formats=[Rows()]))
    calls = []
    gradient = PeVFAAlgorithm.value_chi_gradient
    model.value_chi_gradient = lambda *a: calls.append(1) or gradient(model, *a)  # type: ignore[method-assign]
    model.learn(600, log_interval=2)
    iterations = len(rows) * 2
    assert len(rows) >= 2 and len(calls) == len(rows) < iterations  # every second iteration
    assert all({"pevfa/embedding_norm", "pevfa/value_chi_gradient"} <= set(row) for row in rows)
    calls.clear()
    model.learn(300, log_interval=10**6, reset_num_timesteps=False)  # no row written: nothing computed
    assert not calls


@pytest.mark.parametrize("rule", ["even", "sb3"])
def test_the_diagnostics_conventional_critic_trains_as_the_models_critic(rule):
    """The local-generalization diagnostic's V(s) fits each rollout in the model's minibatches (the authors' even
    split), with its optimizer's settings and its initialization."""
    from sb3_pevfa.diagnostics import LocalGeneralizationCallback

    model = _model((30,), critic_minibatches=rule)
    callback = LocalGeneralizationCallback(net_arch=(128, 128))
    sizes, seen = [], []
    model.learn(150, callback=callback)  # one rollout of 5 episodes: 150 samples
    callback.critic.register_forward_hook(lambda module, inputs, output: sizes.append(len(inputs[0])))
    callback.critic.register_forward_hook(lambda module, inputs, output: seen.append(inputs[0][:, 0].clone()))
    callback._train_critic(th.arange(150.0)[:, None], th.zeros(150))
    assert sizes == ([37] * 4 if rule == "even" else [32, 32, 32, 32, 22]) * 10  # 150 // (150 // 32) = 37
    assert len(th.unique(th.cat(seen))) == 150  # the even split leaves out other samples each epoch
    assert callback.optimizer.defaults["eps"] == 1e-8  # theirs (SB3's: 1e-5)
    fresh = LocalGeneralizationCallback(net_arch=(400, 400))
    fresh.init_callback(model)
    second = fresh.critic[2].weight  # 400 x 400
    assert abs(second.std().item() * 400**0.5 - 1) < 0.03 and th.all(fresh.critic[2].bias == 0)


def test_the_even_split_leaves_out_other_samples_each_epoch():
    """The authors' split leaves N - n_batches * (N // n_batches) samples out of each epoch: drawn again each time."""
    model = _model((30,), algorithm="ppo", critic_minibatches="even", history_train_freq=0)
    _rollout(model)  # 150 samples: 4 minibatches of 37 per epoch, 2 left out
    model.rollout_buffer.observations[:, 0, 0] = np.arange(150)  # each sample known by its state
    seen = []
    predict = model.policy.predict_values
    model.policy.predict_values = lambda obs, *a: seen.append(obs.detach().clone()) or predict(obs, *a)  # type: ignore
    model._train_critic_on_rollout()
    assert [len(batch) for batch in seen] == [37] * 40
    assert len(th.unique(th.cat(seen), dim=0)) == 150  # every sample in some epoch


def test_a_full_batch_actor_update_reads_every_envs_samples():
    env = make_vec_env("Pendulum-v1", n_envs=2, seed=0)
    model = PPOPeVFA("MlpPolicy", env, n_steps=32, batch_size=16, n_epochs=3, update_order="critic_first",
                     actor_batch_size="full", representation="none", history_train_freq=0, seed=0)  # fmt: skip
    _rollout(model)
    sizes = []
    evaluate = model.policy.evaluate_actions
    model.policy.evaluate_actions = lambda obs, *a, **k: sizes.append(len(obs)) or evaluate(obs, *a, **k)  # type: ignore
    with model.policy.critic_frozen():
        model._train_actor_critic()
    assert sizes == [64] * 3  # one batch of both envs' 32 steps per epoch


def test_make_authors_env_is_seeded():
    def first(seed: int) -> np.ndarray:
        return make_authors_env("Pendulum-v1", seed=seed).reset()

    assert np.array_equal(first(0), first(0)) and not np.array_equal(first(0), first(1))


@pytest.mark.parametrize("scale", [0.5, 13.0])
def test_a_log_std_learning_rate_scale_other_than_one_has_its_group(scale):
    model = _model(algorithm="ppo", policy_kwargs=dict(log_std_lr_scale=scale))
    group = next(g for g in model.policy.optimizer.param_groups if g.get("name") == "log_std")
    assert group["params"] == [model.policy.log_std] and group["lr"] == pytest.approx(1e-4 * scale)


def test_sb3_s_truncated_minibatch_warning_only_where_an_update_takes_minibatches_of_batch_size():
    """SB3 warns when batch_size does not divide a rollout; the authors' protocol's critic splits its epochs evenly and
    its actor takes the full batch, so no update takes minibatches of batch_size, and no such warning is given. An
    actor minibatch of its own that leaves a truncated one is named; SB3's mechanics keep SB3's warning."""
    env = make_vec_env("Pendulum-v1", n_envs=1, seed=0)

    def warned(**overrides) -> list[str]:
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always")
            PPOPeVFA("MlpPolicy", env, **authors_protocol("ppo_pevfa", **overrides))
        return [str(w.message) for w in caught if "minibatch" in str(w.message) or "mini-batch" in str(w.message)]

    assert warned() == []  # n_steps 2000, batch_size 128: 15 minibatches and a rest of 80 in SB3's split
    assert warned(critic_minibatches="sb3")[0].startswith("You have specified a mini-batch size of 128")
    assert warned(actor_batch_size=None)[0].startswith("You have specified a mini-batch size of 128")
    assert warned(actor_batch_size=300, rollout_episodes=None) == [
        "actor_batch_size=300 leaves a truncated actor minibatch of 200 samples of each rollout of n_steps * n_envs = 2000"
    ]
    assert warned(actor_batch_size=500, rollout_episodes=None) == []
    assert warned(actor_batch_size=300) == []  # the protocol's rollouts of 5 whole episodes vary in size


def test_an_update_fits_the_critic_as_theirs_then_computes_gae_from_it():
    """``train``: 10 epochs of 4 minibatches of 37 (of 150 samples) on 0.5 * MSE to the Monte-Carlo returns with
    Adam at 1e-3, written out (the package's MSE takes the same Adam steps up to its epsilon); then GAE from the
    fitted critic's values; then the actor's update, the critic untouched."""
    model = _model((30,), algorithm="ppo", history_train_freq=0)
    _rollout(model)
    buffer = model.rollout_buffer
    observations, returns = th.as_tensor(buffer.observations[:, 0]), th.as_tensor(buffer.returns[:, 0])
    rollout_values = buffer.values[:, 0].copy()
    policy = copy.deepcopy(model.policy)
    names = [name for name, p in model.policy.named_parameters() if any(p is q for q in model._critic_params)]
    critic = [dict(policy.named_parameters())[name] for name in names]
    optimizer = th.optim.Adam(critic, lr=1e-3, eps=1e-8)
    np.random.seed(3)
    for _ in range(10):
        indices = np.random.permutation(150)
        for start in range(0, 4 * 37, 37):
            index = indices[start : start + 37]
            loss = 0.5 * ((policy.predict_values(observations[index]).flatten() - returns[index]) ** 2).mean()
            optimizer.zero_grad()
            loss.backward()
            optimizer.step()
    np.random.seed(3)
    model.train()
    ours = dict(model.policy.named_parameters())
    for name, theirs in zip(names, critic):
        assert (ours[name] - theirs).abs().max().item() <= 1e-6, name
    with th.no_grad():
        values = model.policy.predict_values(observations).flatten().numpy()
    assert np.abs(values - rollout_values).max() > 0.1  # the fit moved the critic
    np.testing.assert_allclose(buffer.values[:, 0], values, atol=1e-6)  # GAE read the fitted critic's values
    expected = _gae_of_episodes(values, episodes=5, gamma=0.99, gae_lambda=0.95)
    np.testing.assert_allclose(buffer.advantages[:, 0], expected, rtol=1e-4, atol=1e-5)
