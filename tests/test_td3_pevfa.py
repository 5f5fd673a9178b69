"""TD3PeVFA: its snapshots' smoothed actions (bit for bit TD3 without a representation: tests/test_sac_pevfa.py)."""

import numpy as np
import pytest
import torch as th
from test_sac_pevfa import LEARNED, deterministic, snapshot_then_move_on, tiny

from sb3_pevfa.td3_pevfa import TD3PeVFA


@pytest.mark.parametrize("representation", LEARNED)
def test_a_snapshots_target_uses_its_own_smoothed_action_and_the_actor_gets_no_gradient_through_chi(representation):
    model = TD3PeVFA("MlpPolicy", "Pendulum-v1", **deterministic(representation), history_train_freq=5,
                     history_batch_size=32, history_batch_policies=4, **tiny())  # fmt: skip
    model.learn(200)
    snapshot, records, observations, features = snapshot_then_move_on(model)
    th.manual_seed(5)
    actions, log_prob = model._snapshot_actions(records, features[None])
    th.manual_seed(5)
    noise = th.randn(8, 1).mul_(model.target_policy_noise).clamp_(-model.target_noise_clip, model.target_noise_clip)
    expected = (snapshot(observations) + noise).clamp(-1, 1)
    assert log_prob is None
    np.testing.assert_allclose(actions.detach(), expected.detach(), atol=1e-5)
    assert not th.allclose((model.policy.actor(observations) + noise).clamp(-1, 1), actions, atol=1e-3)
    critic, actor = model.policy.critic, model.policy.actor
    model.policy.zero_grad(set_to_none=True)  # TD3's actor loss: Q1(s, mu(s), chi) with chi of the live actor
    (-critic.q1_forward(observations, actor(observations)).mean()).backward()
    assert all(p.grad is None for p in critic.representation.parameters())  # the encoder learns nothing from it
    through_actions = [p.grad.clone() for p in actor.parameters()]
    model.policy.zero_grad(set_to_none=True)  # the same loss with chi a constant: the actor's gradients are the same
    (-critic.q1_forward(observations, actor(observations), chi=critic.live_embedding().detach()).mean()).backward()
    assert all(th.equal(p.grad, g) for p, g in zip(actor.parameters(), through_actions))


def test_the_smoothed_target_action_is_clipped_to_the_action_bounds():
    """TD3's target smoothing: clip(a + clip(noise, -c, c), -1, 1), the outer clip applied where a + noise leaves [-1, 1]."""
    model = TD3PeVFA("MlpPolicy", "Pendulum-v1", target_policy_noise=0.4, target_noise_clip=0.3, **tiny())
    actions = th.linspace(-0.95, 0.95, 64)[:, None]
    th.manual_seed(0)
    smoothed = model._smoothed(actions)
    th.manual_seed(0)
    noise = th.randn(64, 1).mul_(0.4).clamp_(-0.3, 0.3)
    assert ((actions + noise).abs() > 1).any() and (noise.abs() == 0.3).any()  # both clips apply here
    th.testing.assert_close(smoothed, (actions + noise).clamp(-1, 1), atol=0, rtol=0)
