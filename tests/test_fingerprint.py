"""``representation="fingerprint"``: the actors' action distributions at learned probe states."""

import gymnasium as gym
import numpy as np
import pytest
import torch as th
from conftest import FAST
from stable_baselines3.common.env_util import make_vec_env
from stable_baselines3.common.policies import ActorCriticPolicy
from stable_baselines3.common.vec_env import VecNormalize
from torch import nn

from sb3_pevfa import A2CPeVFA, PolicyRecord, PPOPeVFA
from sb3_pevfa.pevfa.records import ActorLayout, record_policy
from sb3_pevfa.pevfa.representations import FingerprintPolicyRepresentation, make_representation

OBS = gym.spaces.Box(-1, 1, (5,), np.float32)
#: Actors of every action space the fingerprint reads, gSDE (full and per-latent log-std, expln) and ReLU included
ACTORS = {
    "box": (gym.spaces.Box(-1, 1, (2,)), {}),
    "box-relu-1-layer": (gym.spaces.Box(-1, 1, (2, 2)), dict(activation_fn=nn.ReLU, net_arch=dict(pi=[16], vf=[8]))),
    "box-no-hidden-layer": (gym.spaces.Box(-1, 1, (3,)), dict(net_arch=dict(pi=[], vf=[8]))),
    "gsde": (gym.spaces.Box(-1, 1, (2,)), dict(use_sde=True)),
    "gsde-expln": (gym.spaces.Box(-1, 1, (2,)), dict(use_sde=True, use_expln=True, full_std=False, log_std_init=0.5)),
    "discrete": (gym.spaces.Discrete(4), {}),
    "multidiscrete": (gym.spaces.MultiDiscrete([3, 2]), {}),
    "multibinary": (gym.spaces.MultiBinary(3), {}),
}


def _actor(name: str, seed: int) -> ActorCriticPolicy:
    action_space, kwargs = ACTORS[name]
    th.manual_seed(seed)
    return ActorCriticPolicy(OBS, action_space, lambda _: 1e-3, **{"net_arch": dict(pi=[32, 32], vf=[8]), **kwargs})


def _fingerprint(actor: ActorCriticPolicy, n_probes: int = 7) -> FingerprintPolicyRepresentation:
    representation = make_representation("fingerprint", ActorLayout.from_policy(actor), OBS, actor.action_space, 16,
                                         n_probes=n_probes)  # fmt: skip
    with th.no_grad():
        representation.probes.copy_(th.rand(n_probes, OBS.shape[0]) * 2 - 1)
    return representation


def _records(actors: list[ActorCriticPolicy]) -> PolicyRecord:
    layout = ActorLayout.from_policy(actors[0])
    records = [record_policy(actor, layout, None, np.zeros(0)) for actor in actors]
    return PolicyRecord.from_numpy({key: np.stack([r[key] for r in records]) for key in records[0]})


def _distribution_parameters(actor: ActorCriticPolicy, states: th.Tensor) -> th.Tensor:
    """One actor's SB3 distribution at ``states``, read from SB3's own forward (``get_distribution``)."""
    with th.no_grad():
        distribution = actor.get_distribution(states).distribution
    if isinstance(actor.action_space, gym.spaces.Box):
        return th.cat([distribution.mean, distribution.stddev.log()], dim=-1)
    if isinstance(actor.action_space, gym.spaces.MultiDiscrete):
        return th.cat([part.logits for part in distribution], dim=-1)
    return distribution.logits  # torch's Categorical normalises them (log-probabilities); Bernoulli's as they are


@pytest.mark.parametrize("name", sorted(ACTORS))
def test_batched_actors_equal_each_actors_own_forward(name):
    """All actors in one batched pass give what each actor's own SB3 forward gives at the probe states."""
    actors = [_actor(name, seed) for seed in range(4)]
    representation = _fingerprint(actors[0])
    batched = representation.distribution_parameters(_records(actors).params)
    assert batched.shape == (4, 7, representation.n_features)
    for actor, parameters in zip(actors, batched):
        th.testing.assert_close(parameters, _distribution_parameters(actor, representation.probes.detach()), rtol=0, atol=1e-6)


@pytest.mark.parametrize("name", ["box", "gsde", "discrete", "multidiscrete", "multibinary"])
def test_chi_changes_when_the_actor_changes_and_only_then(name):
    actor = _actor(name, 0)
    representation = _fingerprint(actor).eval()
    chi = representation(_records([actor]))
    assert th.equal(representation(_records([actor])), chi)  # the same actor, recorded again
    with th.no_grad():
        actor.value_net.weight.add_(1.0)  # the critic is not the policy
        actor.mlp_extractor.value_net[0].weight.add_(1.0)
    assert th.equal(representation(_records([actor])), chi)
    with th.no_grad():
        actor.mlp_extractor.policy_net[0].weight[3, 1] += 0.1  # one actor weight
    assert not th.allclose(representation(_records([actor])), chi)
    if isinstance(actor.action_space, gym.spaces.Box):
        before = representation(_records([actor]))
        with th.no_grad():
            actor.log_std[0] += 0.1  # the log-std alone
        assert not th.allclose(representation(_records([actor])), before)


def test_value_loss_gradient_reaches_the_probe_states():
    """The value loss of a historical update trains the probe states (the critic learns where to look), not the
    recorded actors."""
    model = PPOPeVFA("MlpPolicy", "Pendulum-v1", representation="fingerprint", **FAST).learn(128)
    policy, history = model.policy, model.history
    observations, targets, policy_ids = history.sample(64)
    records = PolicyRecord.from_numpy(history.records(policy_ids), model.device)
    records = records._replace(params=records.params.requires_grad_(True))
    values = policy.predict_values(th.as_tensor(observations), policy.embed(records))
    policy.optimizer.zero_grad()
    th.nn.functional.mse_loss(values.flatten(), th.as_tensor(targets)).backward()
    probes = policy.representation.probes
    assert probes.grad is not None and probes.grad.abs().sum() > 0
    assert any(p is probes for p in policy.critic_parameters())  # stepped by the critic's optimizer
    assert records.params.grad is not None  # chi reads the actors' parameters ...
    assert all(p.grad is None for p in policy.action_net.parameters())  # ... as records, never the live actor


def test_probes_start_at_the_first_rollout_in_the_actors_input_space():
    """Under VecNormalize the probe states are observations as the actor reads them (normalised): evenly spaced rows
    of the first rollout, env-major; set once, then moved only by the value loss."""
    env = VecNormalize(make_vec_env("Pendulum-v1", n_envs=4, seed=0))
    kwargs = {**FAST, "n_steps": 32, "representation_kwargs": dict(n_probes=16)}
    model = PPOPeVFA("MlpPolicy", env, representation="fingerprint", **kwargs)
    probes = model.policy.representation.probes
    assert not probes.any()
    model.learn(128)  # one rollout; its update has no historical policy, so nothing trains the probes yet
    observations = model.rollout_buffer.observations  # env-major after PPO's update: (4 * 32, 3)
    np.testing.assert_array_equal(probes.detach().numpy(), observations[np.arange(16) * 8])
    raw = np.hypot(probes[:, 0].detach().numpy(), probes[:, 1].detach().numpy())
    assert not np.allclose(raw, 1.0, atol=1e-3)  # not Pendulum's raw (cos, sin)
    first = probes.detach().clone()
    model.learn(256, reset_num_timesteps=False)
    assert model.policy.representation.probes_set == 1.0 and not th.equal(probes, first)


@pytest.mark.parametrize("algorithm", [PPOPeVFA, A2CPeVFA])
def test_resume_equals_uninterrupted_run(tmp_path, algorithm):
    """Model + history saved (the probe states with the policy), RNG states restored: learning on continues bit for
    bit as the uninterrupted run, as ``test_resume_with_history_equals_uninterrupted_run`` for OPR and SPR."""

    def make_env():
        return make_vec_env("Pendulum-v1", n_envs=2, seed=0)

    fast = {**FAST, "n_steps": 32} if algorithm is PPOPeVFA else dict(n_steps=8, history_learning_starts=0, seed=0)
    reference = algorithm("MlpPolicy", make_env(), representation="fingerprint", **fast)
    reference.learn(128)
    reference.save(tmp_path / "model")
    reference.save_history(tmp_path / "history")
    saved_probes = reference.policy.representation.probes.detach().clone()
    reference.set_env(make_env())
    reference.env.seed(reference.seed)
    reference.learn(192, reset_num_timesteps=False)

    resumed = algorithm.load(tmp_path / "model", env=make_env(), restore_rng_state=True)
    assert th.equal(resumed.policy.representation.probes, saved_probes) and resumed.policy.representation.probes_set == 1
    resumed.load_history(tmp_path / "history")
    resumed.learn(192, reset_num_timesteps=False)
    state = [th.cat([p.detach().flatten() for p in model.policy.parameters()]) for model in (resumed, reference)]
    assert th.equal(*state)
    assert not th.equal(resumed.policy.representation.probes, saved_probes)  # they did train


def test_bad_settings_name_what_is_valid():
    actor = _actor("box", 0)
    layout = ActorLayout.from_policy(actor)
    with pytest.raises(ValueError, match=r"representation_kwargs of 'fingerprint' \['n_probe'\], valid choices: \['n_probes'"):
        make_representation("fingerprint", layout, OBS, actor.action_space, n_probe=8)
    with pytest.raises(ValueError, match="n_probes must be a positive int, got 0"):
        make_representation("fingerprint", layout, OBS, actor.action_space, n_probes=0)
    with pytest.raises(TypeError, match=r"supports action spaces \['Box', 'Discrete', 'MultiDiscrete', 'MultiBinary'\]"):
        make_representation("fingerprint", layout, OBS, gym.spaces.Tuple([gym.spaces.Discrete(2)]))
    with pytest.raises(TypeError, match=r"policy_net must be \[nn.Linear, activation\] pairs"):
        make_representation(
            "fingerprint", ActorLayout(layout.linear_shapes, layout.log_std_shape, None), OBS, actor.action_space
        )
    with pytest.raises(ValueError, match="needs a Gaussian actor with a log-std"):
        make_representation("fingerprint", ActorLayout(layout.linear_shapes, ()), OBS, actor.action_space)
    with pytest.raises(ValueError, match="needs representation 'opr' or 'spr'"):
        PPOPeVFA("MlpPolicy", "Pendulum-v1", representation="fingerprint", representation_objectives=("cl",))
