"""SACPeVFA (and what it shares with TD3PeVFA): SB3's SAC with a policy-extended twin critic and critic updates for
snapshots of its actor."""

import copy
import warnings

import numpy as np
import pytest
import torch as th
from conftest import DictPendulum, needs_denormal_flush
from stable_baselines3 import SAC, TD3, HerReplayBuffer
from stable_baselines3.common.distributions import SquashedDiagGaussianDistribution
from stable_baselines3.common.env_util import make_vec_env
from stable_baselines3.common.envs import BitFlippingEnv, FakeImageEnv
from stable_baselines3.common.off_policy_algorithm import OffPolicyAlgorithm
from stable_baselines3.common.save_util import load_from_zip_file
from stable_baselines3.common.torch_layers import BaseFeaturesExtractor
from stable_baselines3.common.type_aliases import DictReplayBufferSamples
from stable_baselines3.common.utils import obs_as_tensor, polyak_update
from stable_baselines3.common.vec_env import VecNormalize
from torch.nn import functional as F

from sb3_pevfa.pevfa import records as record_utils
from sb3_pevfa.pevfa.records import PolicyRecord
from sb3_pevfa.sac_pevfa import SACPeVFA
from sb3_pevfa.td3_pevfa import TD3PeVFA


class Normalized(BaseFeaturesExtractor):
    """Pendulum's observations through a BatchNorm: a features extractor with parameters and running statistics."""

    def __init__(self, observation_space):
        super().__init__(observation_space, 3)
        self.net = th.nn.Sequential(th.nn.Flatten(), th.nn.BatchNorm1d(3))

    def forward(self, observations: th.Tensor) -> th.Tensor:
        return self.net(observations)


def tiny(**policy_kwargs) -> dict:
    """A tiny SAC / TD3: small networks, updates from the 100th step (a new dict each time: SB3 adds keys to it)."""
    return dict(learning_starts=100, batch_size=32, policy_kwargs=dict(net_arch=[32, 32], **policy_kwargs), seed=0)


def _sb3_name(key: str) -> str:
    """Our critic's parameter name as SB3's ContinuousCritic calls it: the stream's layer, then the head's hidden
    layer (its last hidden one) and output."""
    key = key.replace(".stream.", ".")
    return key.replace(".head.hidden.0.", ".2.").replace(".head.output.", ".4.")


@pytest.mark.parametrize("policy", ["MlpPolicy", "MultiInputPolicy", "CnnPolicy"])
@pytest.mark.parametrize(("sb3_class", "pevfa_class"), [(SAC, SACPeVFA), (TD3, TD3PeVFA)])
def test_without_representation_and_snapshot_updates_it_is_sb3_bit_for_bit(sb3_class, pevfa_class, policy):
    def env():
        if policy == "CnnPolicy":
            images = make_vec_env(FakeImageEnv, seed=0, env_kwargs=dict(screen_height=36, screen_width=36, discrete=False))
            images.envs[0].unwrapped.observation_space.seed(0)  # its observations are the space's samples
            return images
        return "Pendulum-v1" if policy == "MlpPolicy" else make_vec_env(DictPendulum, n_envs=1, seed=0)

    images = dict(buffer_size=1000) if policy == "CnnPolicy" else {}
    sb3 = sb3_class(policy, env(), **images, **tiny())
    ours = pevfa_class(policy, env(), representation="none", history_train_freq=0, flush_denormal=False, **images, **tiny())

    def compared() -> tuple[dict, dict]:
        mine = {_sb3_name(k): v for k, v in ours.policy.state_dict().items() if not k.endswith(("_codes", "_states"))}
        return mine, sb3.policy.state_dict()

    mine, theirs = compared()
    assert set(mine) == set(theirs) and all(th.equal(mine[k], theirs[k]) for k in theirs)  # the same initial weights
    for model in (sb3, ours):  # from the same global random states (each constructor seeded them in turn)
        th.manual_seed(1)
        np.random.seed(1)
        model.learn(300)
    mine, theirs = compared()
    assert all(th.equal(mine[k], theirs[k]) for k in theirs), [k for k in theirs if not th.equal(mine[k], theirs[k])]
    assert ours.history.n_policies >= 1  # the snapshots are recorded all the same


@needs_denormal_flush
@pytest.mark.parametrize("pevfa_class", [SACPeVFA, TD3PeVFA])
def test_train_flushes_denormal_adam_moments_and_collecting_does_not(tmp_path, pevfa_class):
    """A moment of a weight without gradient (after a dead ReLU unit) is 0 after ``train`` where denormals are
    flushed, still denormal with ``flush_denormal=False``; the env steps run with IEEE arithmetic; the setting is saved."""
    from sb3_pevfa.pevfa.denormals import denormals_flushed

    for flush in (True, False):
        model = pevfa_class("MlpPolicy", "Pendulum-v1", flush_denormal=flush, **tiny())
        model.learn(101)
        head = model.policy.critic.q_networks[0].head
        with th.no_grad():
            head.hidden[0].weight[0], head.hidden[0].bias[0] = 0.0, -1.0
        state = model.critic.optimizer.state[head.output.weight]
        state["exp_avg"][0, 0] = 1e-40
        seen = []
        collect = model.collect_rollouts
        model.collect_rollouts = lambda *a, collect=collect, seen=seen, **k: (
            seen.append(denormals_flushed()) or collect(*a, **k)
        )  # type: ignore
        model.learn(4, reset_num_timesteps=False)
        moment = state["exp_avg"][0, 0].item()
        assert moment == 0.0 if flush else 0.0 < moment < th.finfo(th.float32).tiny
        assert seen and not any(seen) and not denormals_flushed()
    model.save(tmp_path / "model.zip")
    assert pevfa_class.load(tmp_path / "model.zip").flush_denormal is False
    with pytest.raises(ValueError, match="flush_denormal must be a bool"):
        pevfa_class("MlpPolicy", "Pendulum-v1", flush_denormal=1)


#: The representations whose chi is computed from the live actor by a learned encoder (``random``: a fixed code)
LEARNED = ("opr", "spr", "fingerprint")


def deterministic(representation: str) -> dict:
    """The representation's arguments with chi a function of the actor (SPR: all its pairs, no random subset)."""
    return dict(representation=representation, representation_kwargs=dict(subsample=1.0) if representation == "spr" else None)


@pytest.mark.parametrize("representation", LEARNED)
@pytest.mark.parametrize("live_encoder_gradient", [True, False])
def test_no_gradient_reaches_the_actor_through_its_embedding(live_encoder_gradient, representation):
    model = SACPeVFA("MlpPolicy", "Pendulum-v1", **deterministic(representation), live_encoder_gradient=live_encoder_gradient,
                     **tiny())  # fmt: skip
    model.learn(150)
    observations = th.as_tensor(model.replay_buffer.observations[:16, 0])
    actions = th.as_tensor(model.replay_buffer.actions[:16, 0])
    model.policy.zero_grad(set_to_none=True)
    critic = model.policy.critic
    chi = critic.live_embedding()
    assert chi.shape == (1, 64) and chi.requires_grad  # the encoder learns from the critic's loss
    sum(q.sum() for q in critic(observations, actions)).backward()
    assert all(p.grad is None for p in model.policy.actor.parameters())  # chi of the live actor carries none to it
    encoder_grads = [p.grad is not None and p.grad.abs().sum() > 0 for p in critic.representation.parameters()]
    assert any(encoder_grads) == live_encoder_gradient  # the live critic loss trains the encoder only where asked
    th.manual_seed(1)  # the actor's loss, its sampled actions: no gradient into the encoder
    actions_pi = model.policy.actor(observations)
    model.policy.zero_grad(set_to_none=True)
    sum(q.sum() for q in critic(observations, actions_pi)).backward()
    assert all(p.grad is None for p in critic.representation.parameters())
    through_actions = [p.grad.clone() for p in model.policy.actor.parameters()]
    model.policy.zero_grad(set_to_none=True)  # the same loss with chi of the live actor a constant: the same gradients
    th.manual_seed(1)
    actions_pi = model.policy.actor(observations)
    sum(q.sum() for q in critic(observations, actions_pi, chi=chi.detach())).backward()
    assert all(th.equal(p.grad, g) for p, g in zip(model.policy.actor.parameters(), through_actions))


def test_the_encoder_learns_from_the_live_critic_loss_only_where_asked():
    for live, moved in ((False, False), (True, True)):
        model = SACPeVFA("MlpPolicy", "Pendulum-v1", history_train_freq=0, live_encoder_gradient=live, **tiny())
        before = [p.detach().clone() for p in model.policy.critic.representation.parameters()]
        model.learn(130)
        after = list(model.policy.critic.representation.parameters())
        assert any(not th.equal(b, a) for b, a in zip(before, after)) == moved


def test_a_shared_features_extractor_learns_nothing_from_the_critics_loss():
    model = SACPeVFA("MlpPolicy", "Pendulum-v1", **tiny(features_extractor_class=Normalized, share_features_extractor=True))
    critic = model.policy.critic
    assert critic.features_extractor is model.actor.features_extractor  # as SB3's critic: its features without gradient
    sum(q.sum() for q in critic(th.randn(8, 3), th.rand(8, 1))).backward()
    assert all(p.grad is None for p in critic.features_extractor.parameters())
    assert all(p.grad is not None for p in critic.q_networks[0].parameters())


def test_the_critic_head_adds_chi_as_a_bias_equal_to_the_concatenation():
    model = SACPeVFA("MlpPolicy", "Pendulum-v1", **tiny())
    q_net = model.policy.critic.q_networks[0]
    inputs, chi, pairing = th.randn(12, 4), th.randn(3, 64), th.tensor([0, 2, 1, 1, 0, 2, 2, 2, 0, 1, 0, 0])
    expected = q_net.head(q_net.stream(inputs), chi[pairing])  # the head as the on-policy critic runs it
    th.testing.assert_close(q_net(inputs, chi, pairing), expected, atol=1e-6, rtol=0)
    th.testing.assert_close(q_net(inputs, chi[:1]), q_net.head(q_net.stream(inputs), chi[:1]), atol=1e-6, rtol=0)
    codes = {"paired": chi, "one": chi[:1], "per input": th.randn(12, 64)}
    for name, rows in (("paired", pairing), ("one", None), ("per input", None)):  # the same gradients: head, inputs, chi
        gradients = []
        for forward in (q_net, lambda x, c, r: q_net.head(q_net.stream(x), c if r is None else c[r])):
            x, c = inputs.clone().requires_grad_(), codes[name].clone().requires_grad_()
            output = forward(x, c, rows)
            gradients.append(th.autograd.grad((output**2).sum(), [x, c, *q_net.head.parameters()]))
        for ours, concatenated in zip(*gradients):
            th.testing.assert_close(ours, concatenated, atol=1e-5, rtol=1e-5)
    parameters = list(q_net.head.parameters())
    for x_grad, c_grad in ((False, False), (True, False), (False, True)):  # fewer inputs need a gradient
        gradients = []
        for forward in (q_net, lambda x, c, r: q_net.head(q_net.stream(x), c[r])):
            x, c = inputs.clone().requires_grad_(x_grad), chi.clone().requires_grad_(c_grad)
            wanted = [t for t in (x, c) if t.requires_grad] + parameters
            gradients.append(th.autograd.grad((forward(x, c, pairing) ** 2).sum(), wanted))
        for ours, concatenated in zip(*gradients):
            th.testing.assert_close(ours, concatenated, atol=1e-5, rtol=1e-5)
    gradients = []  # a double backward (a gradient penalty on the inputs) through the head's first layer
    for forward in (q_net, lambda x, c, r: q_net.head(q_net.stream(x), c[r])):
        x = inputs.clone().requires_grad_()
        (input_grad,) = th.autograd.grad(forward(x, chi, pairing).sum(), [x], create_graph=True)
        gradients.append(th.autograd.grad((input_grad**2).sum(), parameters, allow_unused=True))
    for ours, concatenated in zip(*gradients):
        assert (ours is None) == (concatenated is None)
        if ours is not None:
            th.testing.assert_close(ours, concatenated, atol=1e-5, rtol=1e-5)


@pytest.mark.parametrize("fused_actor", [False, True])
def test_the_live_chi_without_gradient_follows_every_step_of_the_actor(fused_actor):
    kwargs = tiny(optimizer_kwargs=dict(fused=True) if fused_actor else None)
    model = SACPeVFA("MlpPolicy", "Pendulum-v1", **kwargs)  # a fused Adam moves weights without version counters
    model.learn(120)
    critic = model.policy.critic
    cached = critic.live_embedding(grad=False)
    assert critic.live_embedding(grad=False) is cached  # computed once while nothing moves
    model.train(1, 32)
    fresh = critic.representation(PolicyRecord.from_numpy({
        "params": critic.layout.flatten(model.policy)[None].numpy(), "states": np.zeros((1, 0)),
        "actions": np.zeros((1, 0)), "codes": critic.behaviour_codes[None].numpy()}))  # fmt: skip
    th.testing.assert_close(critic.live_embedding(grad=False), fresh.detach(), atol=0, rtol=0)
    assert not th.equal(fresh, cached)


def test_the_flat_copy_of_the_actor_is_taken_again_only_when_the_actor_moved(tmp_path):
    model = SACPeVFA("MlpPolicy", "Pendulum-v1", **tiny(optimizer_kwargs=dict(fused=True)))  # no version counters move
    model.learn(120)
    critic, target, observations = model.policy.critic, model.policy.critic_target, th.randn(8, 3)
    params, chi = critic.actor_record().params, critic.live_embedding(grad=False)
    target_params, target_chi = target.actor_record().params, target.live_embedding(grad=False)
    critic.optimizer.zero_grad()
    sum(q.sum() for q in critic(observations, th.zeros(8, 1))).backward()
    critic.optimizer.step()  # the encoder moved, the actor did not
    polyak_update(critic.parameters(), target.parameters(), 0.5)  # SB3's, after the step: it moves no version counter
    assert critic.actor_record().params is params
    fresh = target.representation(target.actor_record()).detach()  # the target's chi through its encoder as it is
    th.testing.assert_close(target.live_embedding(grad=False), fresh, atol=0, rtol=0)
    assert not th.equal(fresh, target_chi)
    moved = critic.live_embedding(grad=False)
    th.testing.assert_close(moved, critic.representation(critic.actor_record()).detach(), atol=0, rtol=0)
    assert not th.equal(moved, chi)
    actor = model.policy.actor
    actor.optimizer.zero_grad()
    actor(observations).sum().backward()
    actor.optimizer.step()
    for module, before in ((critic, params), (target, target_params)):  # both critics read the actor that moved
        assert not th.equal(module.actor_record().params, before)
        th.testing.assert_close(module.actor_record().params[0], critic.layout.flatten(model.policy), atol=0, rtol=0)
    assert target.actor_record().params is critic.actor_record().params  # one copy per move, for both critics
    actor.load_state_dict({name: value + 0.1 for name, value in actor.state_dict().items()})  # without its optimizer
    th.testing.assert_close(critic.actor_record().params[0], critic.layout.flatten(model.policy), atol=0, rtol=0)
    model.save(tmp_path / "model.zip")
    loaded = SACPeVFA.load(tmp_path / "model.zip").policy
    for policy in (loaded, copy.deepcopy(loaded)):  # shared again
        assert policy.critic_target.actor_record().params is policy.critic.actor_record().params
        assert policy.critic_target.actor_generation == policy.critic.actor_generation
        policy.critic.touch_actor()  # one count of the actor's moves for both critics
        assert policy.critic_target.actor_generation == policy.critic.actor_generation


def test_the_critic_optimizer_is_fused_where_it_reads_chi():
    def fused(**kwargs) -> bool:
        return bool(SACPeVFA("MlpPolicy", "Pendulum-v1", **kwargs).policy.critic.optimizer.defaults["fused"])

    assert fused(**tiny()) and fused(representation="random", **tiny())
    assert not fused(representation="none", **tiny())  # SB3's SAC as it is
    assert not fused(**tiny(fused_critic_optimizer=False))
    assert not fused(**tiny(optimizer_kwargs=dict(foreach=True)))  # the user's choice wins


def test_the_training_mode_is_set_in_one_pass_and_the_target_stays_in_evaluation():
    model = SACPeVFA("MlpPolicy", "Pendulum-v1", **tiny())
    policy = model.policy
    for mode in (False, True, False):
        policy.set_training_mode(mode)
        assert policy.training is mode
        assert all(m.training is mode for part in (policy.actor, policy.critic) for m in part.modules())
        assert not any(m.training for m in policy.critic_target.modules())


def snapshot_then_move_on(model) -> tuple:
    """Record a snapshot, then move the live actor away from it: the snapshot's actor (a copy), its record, and 8
    replay observations with their features."""
    snapshot = copy.deepcopy(model.policy.actor)
    policy_id = model.record_snapshot()
    with th.no_grad():
        for param in model.policy.actor.parameters():
            param.add_(0.5 * th.randn_like(param))
    observations = obs_as_tensor(record_utils.rows(model.replay_buffer.observations, (slice(8), 0)), model.device)
    records = PolicyRecord.from_numpy(model.history.records([policy_id]))
    return snapshot, records, observations, model.actor.extract_features(observations, model.actor.features_extractor)


def test_a_snapshots_target_uses_that_snapshots_actions():
    model = SACPeVFA("MlpPolicy", "Pendulum-v1", **tiny())
    model.learn(150)
    snapshot, records, observations, features = snapshot_then_move_on(model)
    th.manual_seed(3)
    actions, log_prob = model._snapshot_actions(records, features[None])
    th.manual_seed(3)
    expected_actions, expected_log_prob = snapshot.action_log_prob(observations)
    np.testing.assert_allclose(actions.detach(), expected_actions.detach(), atol=1e-5)
    np.testing.assert_allclose(log_prob.detach(), expected_log_prob.detach(), atol=1e-4)
    th.manual_seed(3)
    live_actions, _ = model.policy.actor.action_log_prob(observations)
    assert not th.allclose(live_actions, actions, atol=1e-3)  # not the live actor's


def test_snapshots_are_bounded_saved_and_loaded(tmp_path):
    model = SACPeVFA("MlpPolicy", "Pendulum-v1", representation="random", snapshot_freq=20, history_max_policies=3,
                     history_train_freq=4, history_batch_size=32, history_batch_policies=4, **tiny())  # fmt: skip
    model.learn(260)  # 160 gradient steps: 1 + 8 snapshots, the latest 3 kept
    assert model.history.n_policies == 3 and model.history.policy_ids == [6, 7, 8]
    latest_code = model.history.records([8], fields=("codes",))["codes"][0]
    for critic in (model.policy.critic, model.policy.critic_target):  # the target's values read the latest code too
        np.testing.assert_array_equal(critic.behaviour_codes.numpy(), latest_code)
    model.save(tmp_path / "model")
    assert "history" not in load_from_zip_file(tmp_path / "model.zip")[0]  # the snapshots travel apart from the model
    model.save_history(tmp_path / "snapshots")
    loaded = SACPeVFA.load(tmp_path / "model", env=model.get_env())
    loaded.load_history(tmp_path / "snapshots")
    assert loaded.history.policy_ids == [6, 7, 8] and loaded.history_max_policies == 3 and loaded.snapshot_freq == 20
    np.testing.assert_array_equal(loaded.policy.critic_target.behaviour_codes.numpy(), latest_code)
    np.testing.assert_array_equal(loaded.history.records([7])["params"], model.history.records([7])["params"])
    loaded.learn(40, reset_num_timesteps=False)


@pytest.mark.parametrize(("representation", "field", "buffer"), [("random", "codes", "behaviour_codes"),
                                                                ("spr", "states", "pair_states")])  # fmt: skip
def test_loaded_snapshots_give_the_live_actor_the_latest_ones_code_and_states(tmp_path, representation, field, buffer):
    kwargs = dict(representation=representation, n_state_action_pairs=8, snapshot_freq=10, history_train_freq=0)
    model = SACPeVFA("MlpPolicy", "Pendulum-v1", **kwargs, **tiny()).learn(130)
    model.save_history(tmp_path / "snapshots")
    other = SACPeVFA("MlpPolicy", "Pendulum-v1", **kwargs, **tiny())  # a model without snapshots of its own
    other.num_timesteps = model.num_timesteps
    other.load_history(tmp_path / "snapshots")
    latest = model.history.records([model.history.latest_policy_id])[field][0]
    assert other.history.policy_ids == model.history.policy_ids and np.abs(latest).sum() > 0
    for critic in (other.policy.critic, other.policy.critic_target):
        np.testing.assert_array_equal(getattr(critic, buffer).numpy(), latest)


def test_the_target_critics_batch_norm_statistics_follow_the_snapshots_updates():
    """SB3 copies the critic's BatchNorm statistics to its target at each of its updates; the snapshots' updates move
    them after SB3's last copy, so they copy them again (the live ones to the target, not back); they read the actor's
    features in evaluation mode, its statistics unmoved."""
    extractor = dict(features_extractor_class=Normalized, share_features_extractor=False)
    model = SACPeVFA("MlpPolicy", "Pendulum-v1", snapshot_freq=10, history_train_freq=2, history_batch_size=32,
                     history_batch_policies=4, **tiny(**extractor))  # fmt: skip
    model.learn(150)
    statistics = [t.clone() for t in model.batch_norm_stats]
    actor_norm, train, seen = model.actor.features_extractor.net[1], model._train_on_snapshots, []

    def recorded() -> float:  # the actor's statistics before and after the update, the critic's after it
        before = [t.clone() for t in actor_norm.buffers()]
        loss = train()
        seen.append((before, [t.clone() for t in actor_norm.buffers()], [t.clone() for t in model.batch_norm_stats]))
        return loss

    model._train_on_snapshots = recorded  # type: ignore[method-assign]
    model.train(gradient_steps=2, batch_size=32)  # SB3's two steps (each copying the statistics), one snapshots' update
    assert any(not th.equal(a, b) for a, b in zip(statistics, model.batch_norm_stats))
    ((actor_before, actor_after, moved),) = seen
    assert all(th.equal(a, b) for a, b in zip(actor_before, actor_after)) and actor_norm.training  # its mode restored
    for live, target, kept in zip(model.batch_norm_stats, model.batch_norm_stats_target, moved):
        th.testing.assert_close(live, kept, rtol=0, atol=0)
        th.testing.assert_close(target, live, rtol=0, atol=0)


def test_the_snapshots_updates_train_the_critic_at_their_cadence():
    model = SACPeVFA("MlpPolicy", "Pendulum-v1", snapshot_freq=10, history_train_freq=5, history_batch_size=32,
                     history_batch_policies=4, history_learning_starts=150, **tiny())  # fmt: skip
    calls = []
    train = model._train_on_snapshots
    model._train_on_snapshots = lambda: calls.append(train()) or calls[-1]  # type: ignore[method-assign]
    model.learn(300)  # gradient steps from step 100; snapshot updates from step 150: 150 steps -> 30 updates
    assert len(calls) == 30 and model.logger.name_to_value["pevfa/n_history_updates"] == 30  # logged: so far
    before = copy.deepcopy(model.policy.critic.state_dict())
    loss = train()
    assert np.isfinite(loss) and any(not th.equal(v, model.policy.critic.state_dict()[k]) for k, v in before.items())
    model.train(gradient_steps=10, batch_size=32)  # 1 + 10 steps of credit: two updates, their mean loss logged
    assert len(calls) == 32 and calls[-1] != calls[-2]
    assert model.logger.name_to_value["pevfa/history_value_loss"] == pytest.approx(np.mean(calls[-2:]), rel=1e-12)


def test_the_snapshots_updates_start_at_the_env_step_history_learning_starts():
    model = SACPeVFA("MlpPolicy", "Pendulum-v1", history_train_freq=1, history_batch_size=32, history_batch_policies=4,
                     history_learning_starts=120, **tiny())  # fmt: skip
    model.learn(120)  # 20 gradient steps (steps 101-120), the last one's at step 120
    assert model._n_updates == 20 and model._n_history_updates == 1


@pytest.mark.parametrize("pevfa_class", [SACPeVFA, TD3PeVFA])
def test_a_snapshot_update_fits_each_transition_to_its_snapshots_target_written_out(pevfa_class):
    """One snapshot update against SB3's target written out per snapshot k: y = r + gamma (1 - d) (min_j Q'_j(s',
    a'_k, chi_k) [- alpha log pi_k(a'_k | s')]), a'_k from a copy of the actor taken when k was recorded (TD3: its
    smoothed action), the loss of Q_j(s, a, chi_k) on y; the encoder is trained by it, not only by the live loss."""
    model = pevfa_class("MlpPolicy", "Pendulum-v1", representation="opr", snapshot_freq=50, history_train_freq=5,
                        history_batch_size=64, history_batch_policies=2, live_encoder_gradient=False, **tiny())  # fmt: skip
    actors, record = {}, model.record_snapshot

    def recorded() -> int:
        policy_id = record()
        actors[policy_id] = copy.deepcopy(model.actor)
        return policy_id

    model.record_snapshot = recorded  # type: ignore[method-assign]
    if pevfa_class is SACPeVFA:  # log-stds above SB3's clamp (2), where the snapshots' are clamped as SB3's
        model.actor.log_std.bias.data.fill_(5.0)
    else:  # smoothing noise that reaches its clip
        model.target_policy_noise = 1.0
    model.learn(300)  # the snapshot updates train the encoder: its target copy lags behind
    ids = list(actors)[-3:-1]  # two snapshots, neither the live actor
    per_policy = model.history_batch_size // model.history_batch_policies
    data = model.replay_buffer.sample(2 * per_policy)
    # terminal transitions (Pendulum has none) and n-step discounts (SB3's NStepReplayBuffer) of their own
    generator = th.Generator().manual_seed(0)
    dones = (th.rand(data.dones.shape, generator=generator) < 0.3).float()
    discounts = 0.5 + 0.4 * th.rand(data.rewards.shape, generator=generator)
    data = data._replace(dones=dones, discounts=discounts) if "discounts" in data._fields else data._replace(dones=dones)
    discounts = discounts if "discounts" in data._fields else model.gamma  # SB3 < 2.7: no n-step returns
    model.history.sample_policy_ids = lambda n: np.array(ids)  # type: ignore[method-assign]
    model.replay_buffer.sample = lambda n, env=None: data if n == 2 * per_policy else pytest.fail(n)  # type: ignore[method-assign]
    critic, target = model.policy.critic, model.policy.critic_target
    with th.no_grad():
        blocks = [slice(i * per_policy, (i + 1) * per_policy) for i in range(2)]
        records = [PolicyRecord.from_numpy(model.history.records([k])) for k in ids]
        chis = [tuple(m.representation(r) for m in (critic, target)) for r in records]  # (1, embedding) each
        th.manual_seed(3)
        if pevfa_class is SACPeVFA:
            params = [actors[k].get_action_dist_params(data.next_observations[b])[:2] for k, b in zip(ids, blocks)]
            mean, log_std = (th.cat(p) for p in zip(*params))
            next_actions, log_prob = SquashedDiagGaussianDistribution(1).log_prob_from_params(mean, log_std)
            entropy = th.exp(model.log_ent_coef) * log_prob.reshape(-1, 1)
        else:
            mean = th.cat([actors[k](data.next_observations[b]) for k, b in zip(ids, blocks)])
            noise = th.randn_like(mean) * model.target_policy_noise
            assert (noise.abs() > model.target_noise_clip).any()  # the clip binds
            next_actions, entropy = (mean + noise.clamp(-model.target_noise_clip, model.target_noise_clip)).clamp(-1, 1), 0.0
        next_q = th.cat([th.cat(target(data.next_observations[b], next_actions[b], chi), dim=1)
                         for b, (_, chi) in zip(blocks, chis)])  # fmt: skip
        y = data.rewards + (1 - data.dones) * discounts * (next_q.min(dim=1, keepdim=True).values - entropy)
        assert 0 < data.dones.sum() < len(data.dones)
        values = th.cat([th.cat(critic(data.observations[b], data.actions[b], chi), dim=1)
                         for b, (chi, _) in zip(blocks, chis)])  # fmt: skip
        scale = 0.5 if pevfa_class is SACPeVFA else 1.0  # SB3's SAC and TD3 critic losses
        expected = scale * sum(F.mse_loss(values[:, [j]], y) for j in range(values.shape[1]))
    encoder, fit, seen = copy.deepcopy(critic.representation.state_dict()), model.fit_critic, []
    model.fit_critic = lambda values, targets, optimizer: seen.append((values, targets)) or fit(values, targets, optimizer)  # type: ignore[method-assign]
    th.manual_seed(3)
    assert model._train_on_snapshots() == pytest.approx(float(expected), rel=1e-6)
    np.testing.assert_allclose(seen[0][1], y, rtol=1e-6, atol=1e-6)  # each transition's target
    np.testing.assert_allclose(th.cat(seen[0][0], dim=1).detach(), values, rtol=1e-6, atol=1e-6)
    assert any(not th.equal(v, critic.representation.state_dict()[k]) for k, v in encoder.items())


@pytest.mark.parametrize("pevfa_class", [SACPeVFA, TD3PeVFA])
def test_by_default_one_update_of_512_transitions_of_8_snapshots_per_4_gradient_steps(pevfa_class):
    model = pevfa_class("MlpPolicy", "Pendulum-v1", **{**tiny(), "batch_size": 48})
    assert (model.history_batch_size, model.history_batch_policies, model.snapshot_freq) == (512, 8, 1000)
    model.snapshot_freq = 10  # 20 snapshots in the 200 gradient steps below, so that updates draw 8 of them
    sizes, policies = [], []
    sample, records = model.replay_buffer.sample, model.history.records
    model.replay_buffer.sample = lambda n, env=None: sizes.append(n) or sample(n, env)  # type: ignore[method-assign]
    model.history.records = lambda ids, **kw: policies.append(len(ids)) or records(ids, **kw)  # type: ignore[method-assign]
    model.learn(300)  # 200 gradient steps: SB3's 200 batches of 48 and 50 snapshot updates
    assert sizes.count(48) == 200 and len(sizes) == 250 and len(policies) == 50
    # until 8 snapshots exist an update draws them all, 512 / 8 transitions each; then 8 of them, 512 in all
    drawn = [n * 64 for n in policies]
    assert [size for size in sizes if size != 48] == drawn and drawn[-30:] == [512] * 30 and policies[0] == 1


@pytest.mark.parametrize(
    ("kwargs", "message"),
    [
        (dict(representation="rpr"), r"valid choices: \('opr', 'spr', 'fingerprint', 'random', 'none'\)"),
        (dict(representation="spr", n_state_action_pairs=0), "spr' needs n_state_action_pairs > 0"),
        (dict(representation="spr", n_state_action_pairs=16.0), r"n_state_action_pairs must be an int >= 0, got 16.0"),
        (dict(n_state_action_pairs=-1), r"n_state_action_pairs must be an int >= 0, got -1"),
        (dict(embedding_dim=0), "embedding_dim must be a positive int, got 0"),
        (dict(embedding_dim=True), "embedding_dim must be a positive int, got True"),
        (dict(policy_kwargs=dict(critic_embedding_arch=64)), r"critic_embedding_arch must be a list of positive ints"),
        (dict(policy_kwargs=dict(critic_head_arch=[64, 0])), r"critic_head_arch must be a list of positive ints"),
        (dict(snapshot_freq=0), "snapshot_freq must be an int >= 1"),
        (dict(snapshot_freq=10.0), r"snapshot_freq must be an int >= 1, got 10.0"),
        (dict(history_max_policies=0), "history_max_policies must be an int >= 1"),
        (dict(history_train_freq=-1), "history_train_freq must be an int >= 0"),
        (dict(history_batch_size=0), "history_batch_size must be an int >= 1"),
        (dict(history_batch_policies=0), "history_batch_policies must be an int >= 1"),
        (dict(history_learning_starts=-1), "history_learning_starts must be an int >= 0"),
        (dict(history_learning_starts=True), "history_learning_starts must be an int >= 0, got True"),
        (dict(live_encoder_gradient=1), "live_encoder_gradient must be a bool, got 1"),
        (dict(flush_denormal="no"), "flush_denormal must be a bool, got 'no'"),
        (dict(history_batch_size=30, history_batch_policies=8), "must be a multiple of history_batch_policies"),
        (dict(use_sde=True), "use_sde=True is not supported"),
        (dict(policy_kwargs=dict(representation="opr")), r"Pass \['representation'\] as arguments of the algorithm"),
    ],
)
@pytest.mark.parametrize("pevfa_class", [SACPeVFA, TD3PeVFA])
def test_bad_arguments_are_refused_at_construction(pevfa_class, kwargs, message):
    if "use_sde" in kwargs and pevfa_class is TD3PeVFA:  # TD3 has no gSDE option
        message = r"TD3PeVFA\(\) got an unexpected keyword argument 'use_sde'"
    with pytest.raises(ValueError if pevfa_class is SACPeVFA or "use_sde" not in kwargs else TypeError, match=message):
        pevfa_class("MlpPolicy", "Pendulum-v1", **kwargs)


@pytest.mark.parametrize("pevfa_class", [SACPeVFA, TD3PeVFA])
def test_representation_kwargs_of_another_type_are_refused_with_a_type_error(pevfa_class):
    with pytest.raises(TypeError, match=r"^representation_kwargs must be a dict, got list$"):
        pevfa_class("MlpPolicy", "Pendulum-v1", representation_kwargs=[("layer_arch", (8,))])


@pytest.mark.parametrize("pevfa_class", [SACPeVFA, TD3PeVFA])
def test_a_policy_name_it_does_not_take_is_refused_with_the_valid_ones(pevfa_class):
    """SB3's "Policy X unknown" names no choice."""
    name, valid = pevfa_class.__name__, r"valid choices: \['CnnPolicy', 'MlpPolicy', 'MultiInputPolicy'\]$"
    with pytest.raises(ValueError, match=rf"^Unknown policy 'MlpPolicyy' for {name}, {valid}"):
        pevfa_class("MlpPolicyy", "Pendulum-v1")


@pytest.mark.parametrize("pevfa_class", [SACPeVFA, TD3PeVFA])
def test_spr_refuses_images_which_the_other_representations_take(pevfa_class):
    env = make_vec_env(FakeImageEnv, seed=0, env_kwargs=dict(screen_height=36, screen_width=36, discrete=False))
    with pytest.raises(ValueError, match=r"^representation='spr' does not support image observations"):
        pevfa_class("CnnPolicy", env, representation="spr", buffer_size=100)
    model = pevfa_class("CnnPolicy", env, representation="fingerprint", buffer_size=100, **tiny())
    model.learn(101)  # one gradient step, then the first snapshot: its probes, the CNN's features of 32 replay rows
    representation, rows = model.policy.critic.representation, np.arange(32) * 100 // 32
    with th.no_grad():
        features = model.actor.extract_features(
            th.as_tensor(model.replay_buffer.observations[rows, 0]), model.actor.features_extractor
        )
    assert bool(representation.probes_set) and features.shape == (32, model.actor.features_dim)
    th.testing.assert_close(representation.probes.detach(), features, atol=0, rtol=0)


@pytest.mark.parametrize("pevfa_class", [SACPeVFA, TD3PeVFA])
def test_an_unknown_policy_argument_is_named_with_the_closest_valid_ones(pevfa_class):
    """SB3's own TypeError would name SB3's policy class and no valid name."""
    where = rf"^{pevfa_class.__name__}Policy\(\) \(policy_kwargs\)"
    unknown = r"got an unexpected keyword argument 'critic_combine'; did you mean 'critic_embedding_arch'\?$"
    with pytest.raises(TypeError, match=f"{where} {unknown}"):
        pevfa_class("MlpPolicy", "Pendulum-v1", policy_kwargs=dict(critic_combine="product"))


def test_a_policy_subclass_passes_sb3_arguments_its_own_signature_does_not_list():
    """An SB3-style subclass with a fixed signature that sets SB3's arguments itself (the check reads SB3's)."""
    from sb3_pevfa.sac_pevfa import SACPeVFAPolicy

    class Narrow(SACPeVFAPolicy):
        def __init__(self, observation_space, action_space, lr_schedule, use_sde=False, representation="opr",
                     embedding_dim=64, representation_kwargs=None, n_state_action_pairs=200):  # fmt: skip
            pevfa = dict(representation=representation, embedding_dim=embedding_dim,
                         representation_kwargs=representation_kwargs, n_state_action_pairs=n_state_action_pairs)  # fmt: skip
            super().__init__(observation_space, action_space, lr_schedule, use_sde=use_sde, net_arch=[16, 16], **pevfa)

    model = SACPeVFA(Narrow, "Pendulum-v1", learning_starts=10, batch_size=8)
    assert model.policy.net_arch == [16, 16]
    model.learn(20)


class Wider(BaseFeaturesExtractor):
    """Pendulum's 3 observations to 8 features."""

    def __init__(self, observation_space):
        super().__init__(observation_space, 8)
        self.net = th.nn.Sequential(th.nn.Flatten(), th.nn.Linear(3, 8))

    def forward(self, observations: th.Tensor) -> th.Tensor:
        return self.net(observations)


@pytest.mark.parametrize("pevfa_class", [SACPeVFA, TD3PeVFA])
def test_spr_refuses_features_that_are_not_the_flattened_observation(pevfa_class):
    with pytest.raises(ValueError, match=r"^representation='spr' pairs actions with the flattened observations \(3 "
                       r"values\), which the actor's features extractor maps to 8: use 'opr', 'fingerprint'"):  # fmt: skip
        pevfa_class("MlpPolicy", "Pendulum-v1", representation="spr", policy_kwargs=dict(features_extractor_class=Wider))
    pevfa_class("MlpPolicy", "Pendulum-v1", representation="opr", policy_kwargs=dict(features_extractor_class=Wider))


def test_hers_transitions_are_shuffled_before_the_snapshots_share_them(monkeypatch):
    """HER samples its real transitions first and the relabelled ones last: each snapshot gets rows of both."""
    from sb3_pevfa.pevfa import off_policy

    calls = []

    def spied(data):
        calls.append(data)
        return shuffle(data)

    shuffle = off_policy.shuffled
    monkeypatch.setattr(off_policy, "shuffled", spied)
    env = make_vec_env(BitFlippingEnv, n_envs=1, seed=0, env_kwargs=dict(n_bits=4, continuous=True))
    her = SACPeVFA("MultiInputPolicy", env, replay_buffer_class=HerReplayBuffer, snapshot_freq=10, **tiny())
    her.learn(150)
    plain = SACPeVFA("MlpPolicy", "Pendulum-v1", snapshot_freq=10, **tiny())
    plain.learn(150)
    assert len(calls) == her._n_history_updates > 0  # every snapshots' update of the HER run, none of the other
    assert type(calls[-1]).__name__ == "DictReplayBufferSamples"
    n = 64  # a batch whose rows say where they came from
    rows = th.arange(n, dtype=th.float32)[:, None]
    data = DictReplayBufferSamples({"a": rows, "b": rows + 1}, 2 * rows, {"a": rows + 100, "b": rows}, rows % 2, 3 * rows)
    mixed = shuffle(data)
    order = mixed.actions[:, 0].long() // 2
    assert sorted(order.tolist()) == list(range(n)) and order.tolist() != list(range(n))  # the rows, in another order
    for got, given in zip(mixed, data):  # each field's rows moved together
        if isinstance(given, dict):
            assert all(th.equal(got[key], given[key][order]) for key in given)
        else:  # n-step discounts: None unless SB3's n-step buffer gives them
            assert th.equal(got, given[order]) if given is not None else got is None


@pytest.mark.parametrize("pevfa_class", [SACPeVFA, TD3PeVFA])
def test_learning_on_without_the_snapshots_warns_where_they_are(tmp_path, pevfa_class):
    model = pevfa_class("MlpPolicy", "Pendulum-v1", **tiny())
    model.learn(120)
    model.save(tmp_path / "model")
    model.save_replay_buffer(tmp_path / "buffer")
    loaded = pevfa_class.load(tmp_path / "model", env=model.get_env())
    with pytest.warns(
        UserWarning, match=r"learns on from 120 steps \(20 updates\) without its snapshots: load_replay_buffer"
    ) as caught:
        loaded.learn(10, reset_num_timesteps=False)
    assert [w.filename for w in caught if "snapshots" in str(w.message)] == [__file__]  # the user's call
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        pevfa_class.load(tmp_path / "model", env=model.get_env()).learn(10)  # a new run: nothing to warn of
        resumed = pevfa_class.load(tmp_path / "model", env=model.get_env())
        resumed.load_replay_buffer(tmp_path / "buffer")
        resumed.learn(10, reset_num_timesteps=False)
        early = pevfa_class("MlpPolicy", "Pendulum-v1", **tiny())
        early.learn(50)  # no update, no snapshot yet: none to lose
        early.learn(10, reset_num_timesteps=False)
        unread = pevfa_class("MlpPolicy", "Pendulum-v1", history_train_freq=0, **tiny())
        unread.learn(120)
        unread.save(tmp_path / "unread")
        pevfa_class.load(tmp_path / "unread", env=model.get_env()).learn(10, reset_num_timesteps=False)  # none read


@pytest.mark.parametrize("policy", ["MlpPolicy", "MultiInputPolicy"])
@pytest.mark.parametrize("pevfa_class", [SACPeVFA, TD3PeVFA])
def test_the_actors_deterministic_actions_at_its_features_are_sb3s(pevfa_class, policy):
    """SPR's pairs: the actor's deterministic actions from its features (the states the snapshots keep), as SB3's
    ``predict`` computes them from observations (SAC: the squashed mean), a Dict's too."""
    env = make_vec_env("Pendulum-v1" if policy == "MlpPolicy" else DictPendulum, n_envs=1, seed=0)
    model = pevfa_class(policy, env, **tiny())
    model.learn(150)
    observations = model.replay_buffer.sample(64).observations
    actor = model.actor
    with th.no_grad():
        features = actor.extract_features(observations, actor.features_extractor)
        expected = model.policy._predict(observations, deterministic=True)
    th.testing.assert_close(model.policy.critic.actor_actions(features), expected, atol=0, rtol=0)
    assert (expected.abs() < 1).all() and expected.std() > 1e-3  # SAC's squashed: inside the bounds, not constant


def test_numpy_ints_are_ints():
    """Counts from numpy or a search space (np.int64) are accepted as the ints they are."""
    counts = dict(snapshot_freq=10, history_max_policies=10, history_train_freq=0, history_batch_size=64,
                  history_batch_policies=8, history_learning_starts=0)  # fmt: skip
    model = SACPeVFA("MlpPolicy", "Pendulum-v1", embedding_dim=np.int64(8), n_state_action_pairs=np.int64(16),
                     representation="spr", **{name: np.int64(value) for name, value in counts.items()})  # fmt: skip
    assert all(type(getattr(model, name)) is int and getattr(model, name) == value for name, value in counts.items())
    assert type(model.policy.critic.representation.embedding_dim) is int and model.policy.critic.pair_states.shape[0] == 16


@pytest.mark.parametrize(("pevfa_class", "base"), [(SACPeVFA, "SAC"), (TD3PeVFA, "TD3")])
def test_sb3s_positional_learning_rate_is_told_to_come_by_keyword(pevfa_class, base):
    with pytest.raises(TypeError, match=rf"got 0.0003: after the env come the PeVFA arguments; pass {base}'s own"):
        pevfa_class("MlpPolicy", "Pendulum-v1", 3e-4)


@pytest.mark.parametrize("representation", ["opr", "spr"])
def test_several_envs_under_vecnormalize(representation):
    from stable_baselines3.common.vec_env import VecNormalize

    env = VecNormalize(make_vec_env("Pendulum-v1", n_envs=2, seed=0))
    model = SACPeVFA("MlpPolicy", env, representation=representation, snapshot_freq=10, history_train_freq=2,
                     history_batch_size=32, history_batch_policies=4, **tiny())  # fmt: skip
    seen = []
    sample = model.replay_buffer.sample
    model.replay_buffer.sample = lambda n, env=None: seen.append((n, env)) or sample(n, env=env)  # type: ignore[method-assign]
    model.learn(300)
    assert model.history.n_policies > 5 and model.logger.name_to_value["pevfa/n_history_updates"] > 0
    # the snapshots' transitions (and SPR's states of each snapshot) in today's normalization, as SB3's
    assert seen and all(e is env for _, e in seen)
    pairs = model.history.n_state_action_pairs
    assert (pairs > 0 and (pairs, env) in seen) == (representation == "spr")


@pytest.mark.parametrize(
    ("pevfa_class", "representation", "her"),
    [(SACPeVFA, "opr", False), (TD3PeVFA, "opr", False), (SACPeVFA, "spr", False), (SACPeVFA, "spr", True)],
)
def test_resume_with_replay_buffer_and_snapshots_equals_the_uninterrupted_run(tmp_path, pevfa_class, representation, her):
    """Model, replay buffer and snapshots saved, RNG states restored: learning on continues bit for bit (the envs
    seeded and reset at the resume in both runs, as SB3's load does); also with HER's replay buffer of a goal env's
    Dict observations (MultiInputPolicy)."""

    def make_env():
        if her:
            return make_vec_env(BitFlippingEnv, n_envs=1, seed=0, env_kwargs=dict(n_bits=4, continuous=True))
        return make_vec_env("Pendulum-v1", n_envs=1, seed=0)

    kwargs = dict(snapshot_freq=20, history_train_freq=2, history_batch_size=32, history_batch_policies=4,
                  representation=representation, n_state_action_pairs=8, **tiny())  # fmt: skip
    if her:
        kwargs.update(replay_buffer_class=HerReplayBuffer, replay_buffer_kwargs=dict(n_sampled_goal=2))
    reference = pevfa_class("MultiInputPolicy" if her else "MlpPolicy", make_env(), **kwargs)
    reference.learn(200)
    reference.save(tmp_path / "model")
    reference.save_replay_buffer(tmp_path / "replay_buffer")  # the snapshots beside it
    assert (tmp_path / "replay_buffer.snapshots.npz").exists()
    reference.set_env(make_env())
    reference.env.seed(reference.seed)
    reference.learn(100, reset_num_timesteps=False)

    def resumed(with_snapshots: bool):
        model = pevfa_class.load(tmp_path / "model", env=make_env(), restore_rng_state=True)
        if with_snapshots:  # HER's episode under way goes on (its default truncates it: the reference's did not end)
            model.load_replay_buffer(tmp_path / "replay_buffer", truncate_last_traj=False)
        else:  # SB3's replay buffer alone
            OffPolicyAlgorithm.load_replay_buffer(model, tmp_path / "replay_buffer.pkl", truncate_last_traj=False)
        return model.learn(100, reset_num_timesteps=False)

    model = resumed(with_snapshots=True)
    assert model.history.policy_ids == reference.history.policy_ids
    for got, want in zip(model.policy.state_dict().values(), reference.policy.state_dict().values()):
        assert th.equal(got, want)
    without = resumed(with_snapshots=False).policy.state_dict().values()
    assert any(not th.equal(a, b) for a, b in zip(without, reference.policy.state_dict().values()))


@pytest.mark.parametrize("pevfa_class", [SACPeVFA, TD3PeVFA])
def test_spr_records_each_snapshots_deterministic_actions_at_replay_states(pevfa_class):
    model = pevfa_class("MlpPolicy", "Pendulum-v1", representation="spr", n_state_action_pairs=16, **tiny())
    model.learn(150)
    critic = model.policy.critic
    critic.actor_record()  # the live actor's actions at its latest snapshot's states, kept while nothing moves
    model.record_snapshot()  # new states, the actor unmoved: its actions at them
    with th.no_grad():
        expected = model.policy._predict(critic.pair_states, deterministic=True)
    th.testing.assert_close(critic.actor_record().actions[0], expected, atol=0, rtol=0)
    snapshot, records, _, _ = snapshot_then_move_on(model)
    states = records.states[0]
    assert states.shape == (16, 3) and th.equal(model.policy.critic.pair_states, states)  # the live actor's states
    assert th.equal(model.policy.critic_target.pair_states, states)  # its target's too
    with th.no_grad():
        expected = snapshot(states, deterministic=True) if pevfa_class is SACPeVFA else snapshot(states)
    th.testing.assert_close(records.actions[0], expected, atol=1e-6, rtol=0)
    live = model.policy.critic.actor_record()  # the live actor (moved on): its own actions at the same states
    th.testing.assert_close(live.actions[0], model.policy._predict(states, deterministic=True), atol=0, rtol=0)
    assert not th.allclose(live.actions[0], expected, atol=1e-3)


@pytest.mark.parametrize(
    ("n_envs", "buffer_size", "stored", "dict_obs"),
    [(1, 1_000_000, 101, False), (1, 100, 100, False), (2, 1_000_000, 51, False), (2, 1_000_000, 51, True)],
)
@pytest.mark.parametrize("pevfa_class", [SACPeVFA, TD3PeVFA])
def test_the_fingerprint_reads_each_actors_outputs_at_probes_set_from_the_replay_buffer(
    pevfa_class, n_envs, buffer_size, stored, dict_obs
):
    env = make_vec_env(DictPendulum if dict_obs else "Pendulum-v1", n_envs=n_envs, seed=0)
    env = VecNormalize(env) if dict_obs else env  # a Dict's rows as the actor read them: normalised
    policy = "MultiInputPolicy" if dict_obs else "MlpPolicy"
    model = pevfa_class(policy, env, representation="fingerprint", buffer_size=buffer_size, **tiny())
    model.learn(101)  # one gradient step: the first snapshot set the probes, 32 evenly spaced of the rows stored
    representation = model.policy.critic.representation
    rows = np.arange(32) * stored // 32  # a full buffer (100 rows, wrapped once): all its rows; env row % n_envs
    stored = record_utils.rows(model.replay_buffer.observations, (rows, rows % n_envs))
    if dict_obs:  # its keys' rows side by side, in the space's order, normalised
        stored = np.concatenate([env.normalize_obs(stored)[key] for key in ("angle", "speed")], axis=-1)
    expected = th.as_tensor(stored)
    assert bool(representation.probes_set) and th.equal(model.policy.critic_target.representation.probes, expected)
    snapshot, records, _, _ = snapshot_then_move_on(model)
    probes = representation.probes.detach()
    with th.no_grad():
        features = representation.distribution_parameters(records.params)[0]
        if pevfa_class is SACPeVFA:  # the mean and log-std heads
            latent = snapshot.latent_pi(probes)
            wanted = th.cat([snapshot.mu(latent), snapshot.log_std(latent)], dim=1)
        else:  # the deterministic action (the probes are the actor's features)
            wanted = snapshot.mu(probes)
    th.testing.assert_close(features, wanted, atol=1e-5, rtol=0)


@pytest.mark.parametrize("pevfa_class", [SACPeVFA, TD3PeVFA])
def test_a_copied_policy_keeps_its_chi_fresh_and_inference_mode_leaves_no_cache(pevfa_class):
    model = pevfa_class("MlpPolicy", "Pendulum-v1", **tiny())
    model.learn(110)
    policy = copy.deepcopy(model.policy)  # its optimizers come without their step hooks: registered again
    critic = policy.critic
    before = critic.live_embedding(grad=False)
    observations, actions = th.randn(8, 3), th.rand(8, 1)
    loss = sum(q.sum() for q in critic(observations, actions, critic.live_embedding()))
    critic.optimizer.zero_grad()
    loss.backward()
    critic.optimizer.step()  # a fused Adam: the encoder moves without its version counters
    assert not th.equal(critic.live_embedding(grad=False), before)
    with th.inference_mode():
        model.critic(observations, actions)
    model.train(1, 32)  # the update does not meet a tensor cached inside inference mode


def test_a_replay_buffer_whose_snapshots_do_not_load_leaves_the_model_as_it_was(tmp_path):
    model = SACPeVFA("MlpPolicy", "Pendulum-v1", **tiny())
    model.learn(120)
    model.save_replay_buffer(tmp_path / "buffer")
    (tmp_path / "buffer.snapshots.npz").write_text("not a history")
    other = SACPeVFA("MlpPolicy", "Pendulum-v1", **tiny())
    other.learn(105)
    buffer, ids = other.replay_buffer, other.history.policy_ids
    with pytest.raises(ValueError, match=r"buffer\.snapshots\.npz"):
        other.load_replay_buffer(tmp_path / "buffer")
    assert other.replay_buffer is buffer and other.history.policy_ids == ids
    del other.replay_buffer  # none before (SB3's HER test deletes it first): none after
    with pytest.raises(ValueError, match=r"buffer\.snapshots\.npz"):
        other.load_replay_buffer(tmp_path / "buffer")
    assert "replay_buffer" not in vars(other) and other.history.policy_ids == ids


@pytest.mark.parametrize("content", ["a buffer of another task", "not a replay buffer"])
def test_a_replay_buffer_that_does_not_fit_is_refused_and_the_model_keeps_its_own(tmp_path, content):
    """SB3 sets the loaded object as the model's buffer before it checks it, and takes a buffer of other shapes (the
    first transition stored then fails): both are refused, the model's buffer and snapshots kept."""
    from stable_baselines3.common.save_util import save_to_pkl

    if content == "not a replay buffer":
        save_to_pkl(tmp_path / "buffer", {"observations": np.zeros(3)})
        error, message = AssertionError, "The replay buffer must inherit from ReplayBuffer class"
    else:
        other_task = SACPeVFA("MlpPolicy", "MountainCarContinuous-v0", **tiny())
        other_task.learn(10)
        other_task.save_replay_buffer(tmp_path / "buffer")
        error, message = ValueError, (r"buffer\.pkl holds observations of shape \(2,\) and actions of size 1; this "
                                      r"model's are \(3,\) and 1")  # fmt: skip
    model = SACPeVFA("MlpPolicy", "Pendulum-v1", **tiny())
    model.learn(105)
    buffer, ids = model.replay_buffer, model.history.policy_ids
    with pytest.raises(error, match=message):
        model.load_replay_buffer(tmp_path / "buffer")
    assert model.replay_buffer is buffer and model.history.policy_ids == ids


def test_a_failed_save_of_the_replay_buffer_leaves_the_previous_buffer_and_snapshots(tmp_path, monkeypatch):
    model = SACPeVFA("MlpPolicy", "Pendulum-v1", snapshot_freq=10, **tiny())
    model.learn(120)
    model.save_replay_buffer(tmp_path / "buffer")
    files = {path.name: path.read_bytes() for path in tmp_path.iterdir()}
    assert sorted(files) == ["buffer.pkl", "buffer.snapshots.npz"]
    model.learn(30, reset_num_timesteps=False)  # another buffer, more snapshots

    def fails(path):
        with open(path, "wb") as handle:  # a part written, then the disk is full
            handle.write(b"part")
        raise OSError("No space left on device")

    monkeypatch.setattr(model.history, "save", fails)
    with pytest.raises(OSError, match="No space left"):
        model.save_replay_buffer(tmp_path / "buffer")  # the buffer written whole, the snapshots not
    assert {path.name: path.read_bytes() for path in tmp_path.iterdir()} == files  # no new buffer beside old snapshots
    monkeypatch.undo()
    model.save_replay_buffer(tmp_path / "buffer")
    ids = model.history.policy_ids
    model.load_replay_buffer(tmp_path / "buffer")  # the pair of this moment: a buffer of 150 steps, its snapshots
    assert model.replay_buffer.size() == 150 and model.history.policy_ids == ids and len(ids) == 6


def test_a_replay_buffer_is_not_saved_into_a_folder(tmp_path):
    """SB3 would save it beside the folder (``buffer.pkl_2``), away from its snapshots."""
    model = SACPeVFA("MlpPolicy", "Pendulum-v1", **tiny())
    model.learn(105)
    (tmp_path / "buffer.pkl").mkdir()
    with pytest.raises(ValueError, match=r"buffer\.pkl is a folder: save_replay_buffer takes a file path"):
        model.save_replay_buffer(tmp_path / "buffer")
    assert [path.name for path in tmp_path.iterdir()] == ["buffer.pkl"] and not any((tmp_path / "buffer.pkl").iterdir())


def test_a_replay_buffer_saved_to_a_file_object_says_the_snapshots_stay_behind():
    import io

    model = SACPeVFA("MlpPolicy", "Pendulum-v1", **tiny())
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        model.save_replay_buffer(io.BytesIO())  # no snapshot yet: none to lose (SB3's test of file objects)
    model.learn(105)
    stream = io.BytesIO()
    with pytest.warns(UserWarning, match=r"saves the snapshots beside a file path only: save them with save_history"):
        model.save_replay_buffer(stream)
    assert stream.getbuffer().nbytes > 0


def test_the_losses_of_a_train_call_in_pieces_are_logged_as_the_whole_calls_means(monkeypatch):
    """SB3 logs the mean of each loss over a train call's gradient steps: a call run in pieces (snapshots at 20, 40)
    logs their means weighted by the pieces' gradient steps, its counts as SB3 leaves them."""
    model = SACPeVFA("MlpPolicy", "Pendulum-v1", snapshot_freq=20, history_train_freq=0, **tiny())
    model.learn(105)  # 5 gradient steps
    pieces = []

    def sb3_train(self, gradient_steps, batch_size=64):  # SB3's logging of a piece: its losses' means and counts
        pieces.append(gradient_steps)
        self._n_updates += gradient_steps
        self.logger.record("train/n_updates", self._n_updates, exclude="tensorboard")
        self.logger.record("train/learning_rate", 0.25)
        self.logger.record("train/critic_loss", float(len(pieces)))  # 1.0, 2.0, 3.0
        if len(pieces) != 2:
            self.logger.record("train/actor_loss", 10.0 * len(pieces))  # none in the second piece (TD3's delay)

    monkeypatch.setattr(SAC, "train", sb3_train)
    model.train(50, 32)  # from 5 updates: pieces of 15, 20 and 15 gradient steps
    assert pieces == [15, 20, 15] and model._n_updates == 55
    logged = model.logger.name_to_value
    assert logged["train/critic_loss"] == pytest.approx((15 * 1 + 20 * 2 + 15 * 3) / 50)
    assert logged["train/actor_loss"] == pytest.approx((15 * 10 + 15 * 30) / 30)
    assert logged["train/n_updates"] == 55 and logged["train/learning_rate"] == 0.25
    model.train(1, 32)  # one piece: SB3's values as they are
    assert logged["train/critic_loss"] == 4.0 and logged["train/actor_loss"] == 40.0


@pytest.mark.parametrize("pevfa_class", [SACPeVFA, TD3PeVFA])
def test_a_snapshot_every_snapshot_freq_gradient_steps_when_a_train_call_spans_several(pevfa_class):
    """With 50 gradient steps per call and a snapshot per 20, SB3's update runs in pieces ending where one is due."""
    model = pevfa_class("MlpPolicy", "Pendulum-v1", snapshot_freq=20, train_freq=50, gradient_steps=50,
                        history_train_freq=0, **tiny())  # fmt: skip
    model.learn(300)  # train calls after steps 150, 200, 250, 300: 200 gradient steps
    assert model._n_updates == 200
    moments = [model.history.record_info(i)["n_updates"] for i in model.history.policy_ids]
    assert moments == [20, 40, 60, 80, 100, 120, 140, 160, 180, 200]


def test_a_checkpoint_resumes_with_the_replay_buffer_and_snapshots_of_its_moment(tmp_path):
    """rl-zoo3's ``-i`` on a checkpoint asks for the run's final ``replay_buffer.pkl``: the buffer and snapshots that
    SB3's CheckpointCallback(save_replay_buffer=True) saved at the checkpoint's step are loaded instead; without them,
    the final snapshots load with a warning that they come from after the model."""
    from stable_baselines3.common.callbacks import CheckpointCallback

    model = SACPeVFA("MlpPolicy", "Pendulum-v1", snapshot_freq=20, **tiny())
    callback = CheckpointCallback(save_freq=150, save_path=str(tmp_path), name_prefix="rl_model", save_replay_buffer=True)
    model.learn(300, callback=callback)
    model.save_replay_buffer(tmp_path / "replay_buffer.pkl")  # the final one, as --save-replay-buffer writes it
    assert (tmp_path / "rl_model_replay_buffer_150_steps.snapshots.npz").exists()
    at_150 = [i for i in model.history.policy_ids if model.history.record_info(i)["num_timesteps"] <= 150]
    assert 1 < len(at_150) < len(model.history.policy_ids)
    checkpoint = SACPeVFA.load(tmp_path / "rl_model_150_steps.zip")
    with pytest.warns(UserWarning, match="saved with the checkpoint at 150 steps: .*rl_model_replay_buffer_150") as caught:
        checkpoint.load_replay_buffer(tmp_path / "replay_buffer")  # what rl-zoo3's -i does
    assert [w.filename for w in caught] == [__file__]  # said at the user's call, whatever the verbosity
    # SB3 calls the callback before it stores the step's transition: 149 of them at the checkpoint
    assert checkpoint.replay_buffer.size() == 149 and checkpoint.history.policy_ids == at_150
    # another run's checkpoint of the same step in the folder: which one is this model's is not known, none is guessed
    other = tmp_path / "other_replay_buffer_150_steps.pkl"
    other.write_bytes((tmp_path / "rl_model_replay_buffer_150_steps.pkl").read_bytes())
    with pytest.warns(UserWarning, match="Several checkpoints .* saved at 150 steps"):
        checkpoint.load_replay_buffer(tmp_path / "replay_buffer")
    assert checkpoint.replay_buffer.size() == 300  # the asked file (its snapshots warn that they come from after it)
    other.unlink()
    fresh = SACPeVFA("MlpPolicy", "Pendulum-v1", snapshot_freq=20, **tiny())
    fresh.num_timesteps = 300  # the final model, whose step is also a checkpoint's: its own buffer, not the checkpoint's
    fresh.load_replay_buffer(tmp_path / "replay_buffer")
    assert fresh.replay_buffer.size() == 300 and fresh.history.policy_ids == model.history.policy_ids
    (tmp_path / "rl_model_replay_buffer_150_steps.pkl").unlink()  # rl-zoo3's --save-freq saves no buffer
    with pytest.warns(UserWarning, match="recorded up to 300 steps, this model is at 150") as caught:
        checkpoint.load_replay_buffer(tmp_path / "replay_buffer")
    assert [w.filename for w in caught if "recorded up to" in str(w.message)] == [__file__]  # the user's call
    assert checkpoint.replay_buffer.size() == 300 and checkpoint.history.policy_ids == model.history.policy_ids


@pytest.mark.parametrize("pevfa_class", [SACPeVFA, TD3PeVFA])
def test_the_documented_resume_equals_one_uninterrupted_learn(tmp_path, pevfa_class):
    """docs/off-policy.md's resume: loaded onto the same env without a reset (``force_reset=False``), with the RNG
    states, the replay buffer and the snapshots, learning goes on as one ``learn`` call would have."""
    kwargs = dict(snapshot_freq=20, history_train_freq=3, history_batch_size=32, history_batch_policies=4, **tiny())
    reference = pevfa_class("MlpPolicy", "Pendulum-v1", **kwargs).learn(300)
    model = pevfa_class("MlpPolicy", "Pendulum-v1", **kwargs).learn(200)
    credit = model._history_credit  # gradient steps towards the next snapshots' update: 100 % 3
    assert credit == 1
    model.save(tmp_path / "model")
    model.save_replay_buffer(tmp_path / "buffer")
    model = pevfa_class.load(tmp_path / "model", env=model.get_env(), force_reset=False, restore_rng_state=True)
    assert model._history_credit == credit
    model.load_replay_buffer(tmp_path / "buffer")
    model.learn(100, reset_num_timesteps=False)
    assert model.history.policy_ids == reference.history.policy_ids
    for got, want in zip(model.policy.state_dict().values(), reference.policy.state_dict().values()):
        assert th.equal(got, want)
