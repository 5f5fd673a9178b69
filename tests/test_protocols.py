"""The paper's protocol (sb3_pevfa.protocols): the numbers of its Tables 2 and 3, and a PPO baseline that is exactly
PPO with a conventional 2x128 critic updated first."""

import math

import numpy as np
import pytest
import torch as th
from conftest import actor_parameters
from stable_baselines3 import PPO
from stable_baselines3.common.logger import configure
from torch import nn

from sb3_pevfa import PPOPeVFA
from sb3_pevfa.protocols import paper_protocol

SMALL = dict(n_steps=256, batch_size=64, n_epochs=2)


def _linear_shapes(module: nn.Module) -> list[tuple[int, int]]:
    return [tuple(m.weight.shape) for m in module.modules() if isinstance(m, nn.Linear)]


def _activations(module: nn.Module) -> set[type]:
    return {type(m) for m in module.modules() if not list(m.children()) and not isinstance(m, (nn.Linear, nn.Identity))}


@pytest.mark.parametrize("algorithm", ["ppo", "ppo_pevfa"])
def test_paper_protocol_builds_the_papers_networks_and_optimizers(algorithm):
    model = PPOPeVFA("MlpPolicy", "Hopper-v5", **paper_protocol(algorithm), seed=0)
    policy = model.policy
    # Table 2: 2000 steps per iteration, batch 128, 10 epochs, clip 0.2, GAE 0.95, gamma 0.99, Monte-Carlo targets,
    # critic first, no gradient clipping, actor 1e-4 and critic 1e-3 in Adam
    assert (model.n_steps, model.batch_size, model.n_epochs, model.gamma, model.gae_lambda) == (2000, 128, 10, 0.99, 0.95)
    assert model.clip_range(1.0) == 0.2 and model.value_target_lambda == 1.0 and model.update_order == "critic_first"
    assert model.max_grad_norm == math.inf and model.ent_coef == 0.0
    assert [group.get("name") for group in policy.optimizer.param_groups] == ["actor", "critic"]
    assert (model.lr_schedule(1.0), model.critic_lr_schedule(1.0)) == (1e-4, 1e-3)
    assert isinstance(policy.optimizer, th.optim.Adam)
    # the actor: 2x64 ReLU, a state-independent log-std, nothing shared with the critic
    assert _linear_shapes(policy.mlp_extractor.policy_net) == [(64, 11), (64, 64)]
    assert _activations(policy.mlp_extractor.policy_net) == {nn.ReLU} and policy.log_std.shape == (3,)
    assert policy.ortho_init is False and th.equal(policy.log_std.detach(), th.zeros(3)) and model.normalize_advantage
    actor_ids = {id(p) for p in (*policy.mlp_extractor.policy_net.parameters(), *policy.action_net.parameters())}
    assert not actor_ids & {id(p) for p in policy.critic_parameters()}
    head = policy.value_net
    if algorithm == "ppo":  # 2x128 ReLU on the state alone: no chi, no encoder, no history
        assert _linear_shapes(policy.mlp_extractor.value_net) + _linear_shapes(head) == [(128, 11), (128, 128), (1, 128)]
        assert head.embedding_net is None and not list(policy.representation.parameters())
        assert model.history_train_freq == 0 and model.history_max_policies == 1
    else:  # Fig. 7: state -> 64 and chi (64) -> 64, concatenated -> 128 -> 1, all ReLU, chi as OPR gives it
        assert _linear_shapes(policy.mlp_extractor.value_net) == [(64, 11)]
        assert _linear_shapes(head.embedding_net) == [(64, 64)] and _linear_shapes(head.hidden) == [(128, 128)]
        assert isinstance(head.chi_norm, nn.Identity) and policy.representation_name == "opr"
        assert (model.history_buffer_size, model.history_batch_size, model.history_train_freq) == (200_000, 64, 10)
        assert model.history_batch_policies is None and model.history_learning_starts == 5_000
        assert model.rollout_encoder_gradient is True and policy.embedding_dim == 64
    assert {nn.ReLU} == _activations(policy.mlp_extractor.value_net) | _activations(head)


def test_paper_protocol_overrides_and_errors():
    arguments = paper_protocol("ppo_pevfa", representation="spr", policy_kwargs=dict(critic_head_arch=[32]))
    assert arguments["representation"] == "spr" and arguments["policy_kwargs"]["critic_head_arch"] == [32]
    assert arguments["policy_kwargs"]["activation_fn"] is nn.ReLU  # the rest of policy_kwargs kept
    assert paper_protocol("ppo_pevfa")["policy_kwargs"]["critic_head_arch"] == [128]  # the defaults not mutated
    with pytest.raises(ValueError, match="valid choices: \\['ppo', 'ppo_pevfa'\\]"):
        paper_protocol("a2c")


def test_paper_ppo_trains_no_history_and_no_representation():
    model = PPOPeVFA("MlpPolicy", "Pendulum-v1", **paper_protocol("ppo", **SMALL), seed=0)
    model.learn(3 * 256)
    assert model.history.n_policies == 1 and model.history.n_samples == 0  # the current policy's record only
    assert model.logger.name_to_value["pevfa/history_updates"] == 0


def test_paper_ppo_actor_update_equals_sb3_ppo_given_the_same_critic():
    """After the critic's epochs and the advantages they give, the paper's PPO updates its actor exactly as SB3's PPO
    does on the same rollout (actor learning rate 1e-4, no gradient clipping)."""
    model = PPOPeVFA("MlpPolicy", "Pendulum-v1", **paper_protocol("ppo", **SMALL), seed=0)
    _, callback = model._setup_learn(256)
    model.collect_rollouts(model.env, callback, model.rollout_buffer, model.n_steps)
    model._train_critic_on_rollout()
    model._recompute_advantages()
    sb3 = PPO("MlpPolicy", "Pendulum-v1", learning_rate=1e-4, max_grad_norm=math.inf, seed=0, **SMALL,
              policy_kwargs=dict(net_arch=dict(pi=[64, 64], vf=[128]), activation_fn=nn.ReLU, ortho_init=False))  # fmt: skip
    sb3.set_logger(configure(None, []))
    actor = ("mlp_extractor.policy_net", "action_net", "log_std")
    sb3.policy.load_state_dict({k: v for k, v in model.policy.state_dict().items() if k.startswith(actor)}, strict=False)
    for name in ("observations", "actions", "rewards", "advantages", "returns", "episode_starts", "log_probs", "values"):
        setattr(sb3.rollout_buffer, name, getattr(model.rollout_buffer, name).copy())
    sb3.rollout_buffer.full = True
    before = actor_parameters(model.policy)
    for train in (lambda: PPO.train(sb3), model._train_actor_critic):
        th.manual_seed(3)
        np.random.seed(3)
        with model.policy.critic_frozen():
            train()
    after = actor_parameters(model.policy)
    assert not th.allclose(after, before)
    np.testing.assert_allclose(model.policy.layout.flatten(sb3.policy).numpy(), after.numpy(), atol=1e-6)
