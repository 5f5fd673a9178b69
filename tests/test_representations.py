import gymnasium as gym
import numpy as np
import pytest
import torch as th
from stable_baselines3.common.policies import ActorCriticPolicy

from sb3_pevfa.pevfa.critics import PeVFAValueHead
from sb3_pevfa.pevfa.records import ActorLayout, PolicyRecord, record_policy
from sb3_pevfa.pevfa.representations import (
    REPRESENTATIONS,
    OriginPolicyRepresentation,
    make_representation,
)

BOX_OBS = gym.spaces.Box(-1, 1, (3,), np.float32)


def _policy(action_space, net_arch=(64, 64), seed=0) -> ActorCriticPolicy:
    th.manual_seed(seed)
    return ActorCriticPolicy(BOX_OBS, action_space, lambda _: 1e-3, net_arch=dict(pi=list(net_arch), vf=[8]))


def _data(policies, n_pairs=16, code_dim=0) -> PolicyRecord:
    layout = ActorLayout.from_policy(policies[0])
    probe = np.random.default_rng(0).uniform(-1, 1, (n_pairs, 3)).astype(np.float32)
    records = [record_policy(p, layout, probe, np.zeros(code_dim)) for p in policies]
    return PolicyRecord.from_numpy({k: np.stack([r[k] for r in records]) for k in records[0]})


@pytest.mark.parametrize(
    "action_space",
    [gym.spaces.Box(-1, 1, (2,)), gym.spaces.Discrete(4), gym.spaces.MultiDiscrete([3, 2]), gym.spaces.MultiBinary(3)],
)
@pytest.mark.parametrize("net_arch", [(64, 64), (16,), (8, 8, 8)])
def test_layout_any_depth_and_head(action_space, net_arch):
    policy = _policy(action_space, net_arch)
    layout = ActorLayout.from_policy(policy)
    assert len(layout.linear_shapes) == len(net_arch) + 1
    assert layout.n_params == sum(
        p.numel() for n, p in policy.named_parameters() if "policy_net" in n or "action_net" in n
    ) + (policy.log_std.numel() if hasattr(policy, "log_std") else 0)
    flat = layout.flatten(policy)
    rows, log_std = layout.split(flat.unsqueeze(0))
    assert th.equal(rows[-1][0, :, :-1], policy.action_net.weight)
    assert th.equal(rows[-1][0, :, -1], policy.action_net.bias)
    assert (log_std is not None) == isinstance(action_space, gym.spaces.Box)
    for name in REPRESENTATIONS:
        rep = make_representation(name, layout, BOX_OBS, action_space, embedding_dim=8)
        out = rep(_data([policy, _policy(action_space, net_arch, seed=1)], code_dim=8))
        assert out.shape == (2, rep.embedding_dim)
        assert th.isfinite(out).all()


def test_opr_is_invariant_to_permuting_rows():
    policy = _policy(gym.spaces.Box(-1, 1, (2,)))
    layout = ActorLayout.from_policy(policy)
    rep = OriginPolicyRepresentation(layout, 16)
    data = _data([policy])
    rows, _ = layout.split(data.params.clone())
    codes = rep.layer_codes(data)
    for i, layer in enumerate(rows):
        permuted = data.params.clone()
        permuted_rows, _ = layout.split(permuted)
        permuted_rows[i].copy_(layer[:, th.randperm(layer.shape[1])])
        assert not th.equal(permuted, data.params)
        new_codes = rep.layer_codes(data._replace(params=permuted))
        assert th.allclose(new_codes, codes, atol=1e-5)
    # a different policy gets a different code
    assert not th.allclose(rep(_data([_policy(gym.spaces.Box(-1, 1, (2,)), seed=3)])), rep(data))


def test_opr_row_weights_drop_rows():
    policy = _policy(gym.spaces.Discrete(3))
    layout = ActorLayout.from_policy(policy)
    rep = OriginPolicyRepresentation(layout, 16)
    data = _data([policy])
    full = [th.ones(1, out) for out, _ in layout.linear_shapes]
    assert th.allclose(rep(data, row_weights=full), rep(data), atol=1e-6)
    dropped = [w.clone() for w in full]
    dropped[0][0, :10] = 0
    assert not th.allclose(rep(data, row_weights=dropped), rep(data))


def test_opr_layer_code_of_dropped_rows_is_the_mean_over_the_kept_ones():
    policy = _policy(gym.spaces.Box(-1, 1, (2,)), net_arch=(8, 8))
    layout = ActorLayout.from_policy(policy)
    rep = OriginPolicyRepresentation(layout, 8, layer_arch=(8, 4))
    data = _data([policy])
    weights = [th.ones(1, rows) for rows, _ in layout.linear_shapes]
    weights[0][0, ::2] = 0  # the first layer's odd rows kept
    rows, _ = layout.split(data.params)
    with th.no_grad():
        expected = rep.row_encoders[0](rows[0][:, 1::2]).mean(dim=1)
        assert th.allclose(rep.layer_codes(data, weights)[:, :4], expected, atol=1e-6)


def test_spr_subsamples_only_in_training_mode():
    policy = _policy(gym.spaces.Box(-1, 1, (2,)))
    rep = make_representation("spr", ActorLayout.from_policy(policy), BOX_OBS, policy.action_space, 8)
    data = _data([policy], n_pairs=50)
    rep.eval()
    assert th.equal(rep(data), rep(data))
    rep.train()
    assert not th.allclose(rep(data), rep(data))
    # permuting the pairs does not change the code
    rep.eval()
    perm = th.randperm(50)
    assert th.allclose(rep(data._replace(states=data.states[:, perm], actions=data.actions[:, perm])), rep(data), atol=1e-5)


def test_stats_and_rpr_are_fixed_features():
    policy = _policy(gym.spaces.Box(-1, 1, (2,)))
    layout = ActorLayout.from_policy(policy)
    data = _data([policy])
    rpr = make_representation("rpr", layout, BOX_OBS, policy.action_space)
    assert th.equal(rpr(data), data.params)
    stats = make_representation("stats", layout, BOX_OBS, policy.action_space)
    out = stats(data)
    assert out.shape == (1, 7 * (2 * 3 + 1))
    assert th.isclose(out[0, 0], policy.mlp_extractor.policy_net[0].weight.mean(), atol=1e-6)
    # every weight matrix, bias and the log-std: mean, std, min, quartiles, max (numpy's, by hand)
    two = _data([policy, _policy(gym.spaces.Box(-1, 1, (2,)), seed=1)])
    rows, log_std = layout.split(two.params)
    expected = []
    for tensor in [part for layer in rows for part in (layer[..., :-1], layer[..., -1])] + [log_std]:
        values = tensor.flatten(start_dim=1).double().numpy()
        quantiles = np.quantile(values, [0.0, 0.25, 0.5, 0.75, 1.0], axis=1).T
        expected.append(np.concatenate([values.mean(1, keepdims=True), values.std(1, ddof=1, keepdims=True), quantiles], 1))
    np.testing.assert_allclose(stats(two).numpy(), np.concatenate(expected, axis=1), rtol=1e-5, atol=1e-6)
    assert len(list(stats.parameters())) == 0 and len(list(rpr.parameters())) == 0


def test_bad_representation_arguments():
    policy = _policy(gym.spaces.Box(-1, 1, (2,)))
    layout = ActorLayout.from_policy(policy)
    with pytest.raises(ValueError, match="valid choices"):
        make_representation("opr-cl", layout, BOX_OBS, policy.action_space)
    for dim in (0, -3):
        with pytest.raises(ValueError, match="embedding_dim"):
            make_representation("opr", layout, BOX_OBS, policy.action_space, embedding_dim=dim)
    with pytest.raises(ValueError, match="takes no representation_kwargs"):
        make_representation("rpr", layout, BOX_OBS, policy.action_space, layer_arch=(4,))
    with pytest.raises(ValueError, match=r"representation_kwargs of 'opr' \['unknown'\], valid choices: \['layer_arch'"):
        make_representation("opr", layout, BOX_OBS, policy.action_space, unknown=1)
    with pytest.raises(ValueError, match="subsample"):
        make_representation("spr", layout, BOX_OBS, policy.action_space, subsample=0.0)
    image = gym.spaces.Box(0, 255, (36, 36, 1), np.uint8)
    with pytest.raises(ValueError, match="image"):
        make_representation("spr", layout, image, policy.action_space)


def test_value_head_paper_shape_and_none():
    head = PeVFAValueHead(64, 64, [64], [128])
    layers = [m for m in head.modules() if isinstance(m, th.nn.Linear)]
    assert [(m.in_features, m.out_features) for m in layers] == [(64, 64), (128, 128), (128, 1)]
    assert head(th.zeros(5, 64), th.zeros(1, 64)).shape == (5, 1)
    plain = PeVFAValueHead(64, 0, [64], [128])
    assert plain.embedding_net is None and plain(th.zeros(5, 64), th.zeros(1, 0)).shape == (5, 1)
    product = PeVFAValueHead(32, 16, [64], [128], combine="product")
    assert product(th.zeros(5, 32), th.zeros(5, 16)).shape == (5, 1)
    with pytest.raises(ValueError, match="valid choices"):
        PeVFAValueHead(64, 64, [64], [128], combine="hyper")
    with pytest.raises(ValueError, match="positive"):
        PeVFAValueHead(64, 64, [0], [128])
