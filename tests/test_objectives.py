import math

import gymnasium as gym
import numpy as np
import pytest
import torch as th
from conftest import FAST, actor_parameters, module_parameters, read_progress
from stable_baselines3.common.policies import ActorCriticPolicy

from sb3_pevfa import PPOPeVFA
from sb3_pevfa.pevfa.arguments import PAPER_SCHEDULE
from sb3_pevfa.pevfa.objectives import ActionPredictionObjective, ContrastiveObjective, make_objective
from sb3_pevfa.pevfa.records import ActorLayout, PolicyRecord, record_policy
from sb3_pevfa.pevfa.representations import OriginPolicyRepresentation, make_representation

OBS = gym.spaces.Box(-1, 1, (4,), np.float32)


def _synthetic_policies(action_space, n_policies=48, n_pairs=64, seed=0) -> tuple[ActorLayout, PolicyRecord]:
    """Randomly initialised small actors with decisive action heads, probed at shared random states."""
    rng = np.random.default_rng(seed)
    probe = rng.uniform(-1, 1, (n_pairs, 4)).astype(np.float32)
    records, layout = [], None
    for i in range(n_policies):
        th.manual_seed(seed * 1000 + i)
        policy = ActorCriticPolicy(
            OBS, action_space, lambda _: 1e-3, net_arch=dict(pi=[16, 16], vf=[8]), ortho_init=False, log_std_init=-1.5
        )
        with th.no_grad():
            policy.action_net.weight.mul_(10.0)
        layout = layout or ActorLayout.from_policy(policy)
        records.append(record_policy(policy, layout, probe, np.zeros(0)))
    return layout, PolicyRecord.from_numpy({k: np.stack([r[k] for r in records]) for k in records[0]})


def _train(objective, representation, data, steps, batch, seed=0):
    optimizer = th.optim.Adam([*representation.parameters(), *(p for p in objective.parameters() if p.requires_grad)], lr=1e-3)
    generator = np.random.default_rng(seed)
    for _ in range(steps):
        index = th.as_tensor(generator.choice(len(data.params), size=batch, replace=False))
        loss, _ = objective.loss(representation, PolicyRecord(*(field[index] for field in data)))
        optimizer.zero_grad()
        loss.backward()
        optimizer.step()
        objective.after_step(representation)


@pytest.mark.parametrize("name", ["opr", "spr"])
def test_contrastive_learning_separates_policies(name):
    th.manual_seed(0)
    layout, data = _synthetic_policies(gym.spaces.Box(-1, 1, (2,)))
    representation = make_representation(name, layout, OBS, gym.spaces.Box(-1, 1, (2,)), embedding_dim=32)
    objective = ContrastiveObjective(representation, batch_policies=16)
    batch = PolicyRecord(*(field[:16] for field in data))
    with th.no_grad():
        _, before = objective.loss(representation, batch)
    _train(objective, representation, data, steps=500, batch=16)
    with th.no_grad():
        accuracy = np.mean([objective.loss(representation, batch)[1]["cl_accuracy"] for _ in range(10)])
    # chance is 1/16
    assert accuracy > 0.4 and accuracy > before["cl_accuracy"] + 0.2

    # the momentum encoder follows the online one, slowly: key <- (1 - m) key + m online after each step
    def flat(module):
        return th.cat([p.detach().flatten().clone() for p in module.parameters()])

    online, key = flat(representation), flat(objective.key_encoder)
    assert not th.equal(online, key) and th.allclose(online, key, atol=0.5)
    objective.after_step(representation)
    m = objective.momentum
    th.testing.assert_close(flat(objective.key_encoder), (1 - m) * key + m * online, rtol=1e-5, atol=1e-7)


@pytest.mark.parametrize(
    "action_space", [gym.spaces.Box(-1, 1, (2,)), gym.spaces.Discrete(3), gym.spaces.MultiDiscrete([2, 3])]
)
@pytest.mark.parametrize("name", ["opr", "spr"])
def test_action_prediction_lowers_nll(name, action_space):
    th.manual_seed(0)
    layout, data = _synthetic_policies(action_space)
    representation = make_representation(name, layout, OBS, action_space, embedding_dim=32)
    objective = ActionPredictionObjective(representation, OBS, action_space, pairs_per_policy=16)

    def nll(shuffle=False):
        with th.no_grad():
            embeddings = representation(data)
            if shuffle:  # every policy gets another policy's embedding
                embeddings = embeddings.roll(1, dims=0)
            return objective.negative_log_likelihood(embeddings, data.states, data.actions).item()

    untrained = nll()
    _train(objective, representation, data, steps=300, batch=16)
    assert nll() < untrained - 0.2
    # the decoder relies on the embedding: another policy's embedding predicts this policy's actions worse
    assert nll() < nll(shuffle=True) - 0.1


def _spy_on_encoder(representation) -> list:
    """The (records, row_weights) each call of the encoder received."""
    seen, forward = [], representation.forward

    def spy(records, row_weights=None, **kwargs):
        seen.append((records, row_weights))
        return forward(records, row_weights, **kwargs)

    representation.forward = spy
    return seen


@pytest.mark.parametrize("mask_ratio", [0.0, 1.0])
def test_opr_augmentation_masks_hidden_rows_at_the_mask_ratio_never_the_output_layer(mask_ratio):
    layout, data = _synthetic_policies(gym.spaces.Box(-1, 1, (2,)), n_policies=6, n_pairs=8)
    representation = OriginPolicyRepresentation(layout, 8)
    seen = _spy_on_encoder(representation)
    ContrastiveObjective(representation, batch_policies=2, mask_ratio=mask_ratio)._encode(representation, data)
    ((_, (*hidden, output)),) = seen
    for weights, (rows, _) in zip(hidden, layout.linear_shapes[:-1]):
        assert th.equal(weights, th.full((6, rows), 1.0 - mask_ratio))  # 0: every row kept; 1: every row dropped
    assert th.equal(output, th.ones(6, layout.linear_shapes[-1][0]))


def test_opr_augmentation_draws_its_mask_per_row():
    layout, data = _synthetic_policies(gym.spaces.Box(-1, 1, (2,)), n_policies=32, n_pairs=8)
    representation = OriginPolicyRepresentation(layout, 8)
    seen = _spy_on_encoder(representation)
    th.manual_seed(0)
    ContrastiveObjective(representation, batch_policies=2, mask_ratio=0.5)._encode(representation, data)
    hidden = th.cat(seen[0][1][:-1], dim=1)  # 32 policies x 32 hidden rows
    assert abs(hidden.mean().item() - 0.5) < 0.05  # of 1024 draws
    assert (hidden.min(dim=1).values < hidden.max(dim=1).values).all()  # each policy keeps some rows, drops others


def test_opr_noise_corrupts_a_noise_ratio_of_the_parameters_with_gaussian_noise_of_noise_std():
    layout, data = _synthetic_policies(gym.spaces.Box(-1, 1, (2,)), n_policies=32, n_pairs=8)
    representation = OriginPolicyRepresentation(layout, 8)
    seen = _spy_on_encoder(representation)
    th.manual_seed(0)
    objective = ContrastiveObjective(representation, batch_policies=2, mask_ratio=0.0, noise_ratio=0.5, noise_std=0.3)
    objective._encode(representation, data)
    delta = seen[0][0].params - data.params
    changed = delta != 0
    assert abs(changed.float().mean().item() - 0.5) < 0.02  # of the 32 policies' 388 parameters each
    assert abs(delta[changed].std().item() - 0.3) < 0.02 and abs(delta[changed].mean().item()) < 0.02


def test_the_contrastive_key_is_the_momentum_encoders_and_each_policys_positive_its_own():
    layout, data = _synthetic_policies(gym.spaces.Box(-1, 1, (2,)), n_policies=6, n_pairs=8)
    representation = OriginPolicyRepresentation(layout, 8)
    objective = ContrastiveObjective(representation, batch_policies=2, mask_ratio=0.0)
    with th.no_grad():  # the same encoders at first, W = I, no augmentation: logits Q Q^T, positives on the diagonal
        query = representation(data)
        expected = th.nn.functional.cross_entropy(query @ query.T, th.arange(6))
        assert th.allclose(objective.loss(representation, data)[0], expected, atol=1e-5)
        objective.key_encoder.projection.weight.zero_()  # every key 0: every logit 0, whatever the query
        objective.key_encoder.projection.bias.zero_()
    loss, _ = objective.loss(representation, data)
    assert loss.item() == pytest.approx(math.log(6), abs=1e-6)
    loss.backward()
    assert all(parameter.grad is None for parameter in objective.key_encoder.parameters())


def test_contrastive_defaults_are_the_papers():  # docs/representations.md
    layout, _ = _synthetic_policies(gym.spaces.Box(-1, 1, (2,)), n_policies=1, n_pairs=8)
    opr, spr = (
        ContrastiveObjective(make_representation(name, layout, OBS, gym.spaces.Box(-1, 1, (2,)))) for name in ("opr", "spr")
    )
    assert opr.momentum == spr.momentum == 0.01 and (opr.learning_rate, spr.learning_rate) == (1e-3, 5e-4)
    assert opr.mask_ratio == 0.1 and opr.noise_ratio == 0.0 and spr.sample_ratio == 0.8


def test_the_action_prediction_loss_is_the_mean_nll_per_pair():
    layout, data = _synthetic_policies(gym.spaces.Discrete(3), n_policies=6, n_pairs=8)
    representation = make_representation("opr", layout, OBS, gym.spaces.Discrete(3), embedding_dim=8)
    objective = ActionPredictionObjective(representation, OBS, gym.spaces.Discrete(3), pairs_per_policy=4)
    with th.no_grad():
        objective.action_net.weight.zero_()  # uniform over 3 actions: log 3 per pair, whatever the pairs' number
        objective.action_net.bias.zero_()
        assert objective.loss(representation, data)[0].item() == pytest.approx(math.log(3), abs=1e-6)


def test_an_objective_waits_for_its_learning_starts():
    model = PPOPeVFA("MlpPolicy", "Pendulum-v1", representation_objectives=("cl",),
                     objective_kwargs={"cl": {"learning_starts": 192, "train_freq": 16}}, **FAST)  # fmt: skip
    model.learn(3 * 64)
    # rollouts end at 64, 128 and 192 env steps: only the third has reached 192, and takes 64 // 16 = 4 steps
    assert {int(state["step"]) for state in model.policy.cl_optimizer.state.values()} == {4}


def test_objective_errors():
    layout, _ = _synthetic_policies(gym.spaces.Discrete(2), n_policies=1)
    for name in ("random", "rpr", "stats", "none"):
        representation = make_representation(name, layout, OBS, gym.spaces.Discrete(2), embedding_dim=8)
        with pytest.raises(ValueError, match="needs representation 'opr' or 'spr'"):
            make_objective("cl", representation, OBS, gym.spaces.Discrete(2))
    opr = make_representation("opr", layout, OBS, gym.spaces.Discrete(2))
    with pytest.raises(ValueError, match="valid choices"):
        make_objective("byol", opr, OBS, gym.spaces.Discrete(2))
    with pytest.raises(ValueError, match="momentum"):
        make_objective("cl", opr, OBS, gym.spaces.Discrete(2), momentum=2.0)
    with pytest.raises(ValueError, match="batch_policies"):
        make_objective("aux", opr, OBS, gym.spaces.Discrete(2), batch_policies=0)
    with pytest.raises(ValueError, match=r"Unknown objective_kwargs of 'aux' \['mask_ratio'\], valid choices: \['train_freq'"):
        make_objective("aux", opr, OBS, gym.spaces.Discrete(2), mask_ratio=0.1)
    with pytest.raises(ValueError, match="batch_policies must be an int >= 2"):  # one policy: it would never train
        make_objective("cl", opr, OBS, gym.spaces.Discrete(2), batch_policies=1)
    cases = [
        (dict(representation="random", representation_objectives=("cl",)), "needs representation"),
        (dict(representation_objectives=("cl", "cl")), "twice"),
        (dict(representation_objectives=("contrastive",)), "valid choices"),
        (dict(representation_objectives=("cl",), objective_kwargs={"aux": {}}), "not in representation_objectives"),
        (dict(representation_kwargs=dict(layr_arch=(8,))), r"Unknown representation_kwargs of 'opr' \['layr_arch'\]"),
        (dict(representation="spr", representation_kwargs=dict(sub_sample=0.5)), "valid choices: .*'subsample'"),
        (dict(history_buffer_size=2048), "holds no more than one rollout"),
    ]
    for kwargs, match in cases:
        with pytest.raises(ValueError, match=match):
            PPOPeVFA("MlpPolicy", "CartPole-v1", **kwargs)
    for kwargs, match in [
        (dict(representation_kwargs=[("layer_arch", (8,))]), "representation_kwargs must be a dict, got list"),
        (dict(representation_objectives="cl", objective_kwargs={"cl": 3}), "must map objective names to dicts"),
    ]:
        with pytest.raises(TypeError, match=match):
            PPOPeVFA("MlpPolicy", "CartPole-v1", **kwargs)
    # a single objective as a string is that objective, not its letters
    assert PPOPeVFA("MlpPolicy", "CartPole-v1", representation_objectives="cl").policy.representation_objectives == ("cl",)
    PPOPeVFA("MlpPolicy", "CartPole-v1", history_buffer_size=2048, history_train_freq=0)  # no historical updates: fine


OBJECTIVE_FAST = {"learning_starts": 0, "train_freq": 16}


@pytest.mark.parametrize("env_id", ["CartPole-v1", "Pendulum-v1"])
@pytest.mark.parametrize("representation", ["opr", "spr"])
@pytest.mark.parametrize("objectives", [("cl",), ("aux",), ("cl", "aux")])
def test_objectives_in_training(env_id, representation, objectives, csv_logger):
    model = PPOPeVFA(
        "MlpPolicy",
        env_id,
        representation=representation,
        representation_objectives=objectives,
        objective_kwargs={name: OBJECTIVE_FAST for name in objectives},
        **FAST,
    )
    model.set_logger(csv_logger[0])
    model.learn(256)
    last = read_progress(csv_logger[1])[-1]
    for name in objectives:
        assert int(last[f"pevfa/{name}_updates"]) == 4
    # the objectives' own steps (one iteration's worth) move the encoder and leave the critic head and the actor alone
    policy = model.policy
    policy.set_training_mode(True)
    encoder, head = module_parameters(policy.representation), module_parameters(policy.value_net)
    actor = actor_parameters(policy)
    metrics = model._train_objectives()
    for name in objectives:
        assert len(metrics[f"{name}_updates"]) == 4
    assert not th.equal(module_parameters(policy.representation), encoder)
    assert th.equal(module_parameters(policy.value_net), head) and th.equal(actor_parameters(policy), actor)
    # the logged metrics are the means of the steps' values
    if "cl" in objectives:
        assert 0 <= float(last["pevfa/cl_accuracy"]) <= 1 and float(last["pevfa/cl_loss"]) > 0
        assert {len(metrics["cl_loss"]), len(metrics["cl_accuracy"])} == {4}
    if "aux" in objectives:
        assert len(metrics["aux_nll"]) == 4 and np.isfinite(float(last["pevfa/aux_nll"]))


@pytest.mark.parametrize("named", [("cl", "aux"), ("aux", "cl")])
def test_aux_steps_come_before_cl_steps_as_in_algorithm_3(named, monkeypatch):
    """Algorithm 3's iteration: the AUX steps, then the CL steps, in whichever order the objectives are named."""
    model = PPOPeVFA("MlpPolicy", "Pendulum-v1", representation_objectives=named,
                     objective_kwargs={name: OBJECTIVE_FAST for name in named}, **FAST)  # fmt: skip
    steps = []
    for name, objective in model.policy.objectives.items():

        def loss(*args, _name=name, _loss=objective.loss):
            steps.append(_name)
            return _loss(*args)

        monkeypatch.setattr(objective, "loss", loss)
    model.learn(64 * 3)  # 4 steps of each per iteration; none in the first (one policy recorded: nothing to contrast)
    assert steps == (["aux"] * 4 + ["cl"] * 4) * 2


@pytest.mark.parametrize(
    ("kwargs", "cl_kwargs", "train_freq", "steps"),
    [
        # credit of 64 env steps per iteration; the first iteration has one recorded policy: nothing to contrast
        ({}, {}, 40, 2 + 1),  # PPOPeVFA's historical cadence (40): 88 // 40, then 72 // 40
        (PAPER_SCHEDULE, {}, 10, 6 + 7),  # the paper's schedule: the paper's 10 (68 // 10, then 72 // 10)
        ({"history_train_freq": 0}, {}, 10, 6 + 7),  # no historical updates: the paper's 10
        ({}, {"train_freq": 16}, 16, 4 + 4),  # its own
    ],
)
def test_the_contrastive_objective_follows_the_historical_updates_cadence(kwargs, cl_kwargs, train_freq, steps):
    """CL's ``train_freq=None`` (default) steps on the cadence of the historical critic updates."""
    model = PPOPeVFA("MlpPolicy", "Pendulum-v1", representation_objectives=("cl",),
                     objective_kwargs={"cl": {"learning_starts": 0, **cl_kwargs}},
                     **{**FAST, "history_train_freq": 40, **kwargs})  # fmt: skip
    assert model.objective_train_freq(model.policy.objectives["cl"]) == train_freq
    model.learn(64 * 3)
    assert {int(state["step"]) for state in model.policy.cl_optimizer.state.values()} == {steps}


def test_save_load_with_both_objectives(tmp_path):
    model = PPOPeVFA(
        "MlpPolicy",
        "Pendulum-v1",
        representation="spr",
        representation_objectives=("cl", "aux"),
        objective_kwargs={"cl": {**OBJECTIVE_FAST, "batch_policies": 8}, "aux": OBJECTIVE_FAST},
        **FAST,
    )
    model.learn(192)
    model.save(tmp_path / "model")
    loaded = PPOPeVFA.load(tmp_path / "model")
    assert loaded.policy.representation_objectives == ("cl", "aux")
    assert loaded.policy.objectives["cl"].batch_policies == 8
    for name in ("cl", "aux"):
        saved, restored = getattr(model.policy, f"{name}_optimizer"), getattr(loaded.policy, f"{name}_optimizer")
        assert len(restored.state) == len(saved.state) > 0
        for key, state in saved.state_dict()["state"].items():
            assert th.equal(state["exp_avg"], restored.state_dict()["state"][key]["exp_avg"])
    for (name, a), b in zip(model.policy.state_dict().items(), loaded.policy.state_dict().values()):
        assert th.equal(a, b), name
    assert "objectives.cl.key_encoder.projection.weight" in loaded.policy.state_dict()


@pytest.mark.parametrize("representation", ["opr", "spr"])
def test_objectives_with_gsde(representation):
    """The docs' "Can I use?" table: both objectives train beside a gSDE actor (its log-std is a matrix)."""
    objective_kwargs = {name: dict(learning_starts=0, batch_policies=4, train_freq=16) for name in ("cl", "aux")}
    model = PPOPeVFA("MlpPolicy", "Pendulum-v1", use_sde=True, representation=representation,
                     representation_objectives=("cl", "aux"), objective_kwargs=objective_kwargs, **FAST)  # fmt: skip
    model.learn(256)
    # both took 4 steps in each of iterations 2-4 (the first has a single recorded policy: nothing to contrast)
    for optimizer in (model.policy.cl_optimizer, model.policy.aux_optimizer):
        assert {int(state["step"]) for state in optimizer.state.values()} == {12}


@pytest.mark.parametrize("separate_pairs", [True, False])
def test_spr_and_aux_read_pairs_of_their_own(separate_pairs):
    """The paper keeps separate pairs for SPR and AUX: AUX then predicts the policy's actions at other states than
    the ones chi was computed from, instead of partly reconstructing them."""
    model = PPOPeVFA("MlpPolicy", "Pendulum-v1", representation="spr", representation_objectives=("aux",),
                     objective_kwargs={"aux": {**OBJECTIVE_FAST, "separate_pairs": separate_pairs}}, **FAST)  # fmt: skip
    model.learn(128)
    policy, aux = model.policy, model.policy.objectives["aux"]
    records = PolicyRecord.from_numpy(model.history.records(model.history.policy_ids))
    n = 200
    assert records.states.shape[1] == policy.n_recorded_pairs == (2 * n if separate_pairs else n)
    policy.set_training_mode(False)

    def changed(part: slice) -> PolicyRecord:
        states = records.states.clone()
        states[:, part] += 1.0
        return records._replace(states=states)

    with th.no_grad():
        chi = policy.embed(records)
        # SPR's chi reads the first n pairs only
        assert not th.allclose(policy.embed(changed(slice(0, n))), chi)
        if separate_pairs:
            assert th.equal(policy.embed(changed(slice(n, 2 * n))), chi)
            assert not np.array_equal(records.states[:, :n], records.states[:, n:])  # probe states drawn apart

        class FixedChi(th.nn.Module):  # AUX's decoder inputs without chi's dependence on the pairs
            def forward(self, _records):
                return chi

        def aux_loss(data):
            th.manual_seed(0)
            return aux.loss(FixedChi(), data)[0].item()

        # AUX decodes the second n pairs (separate) or SPR's own pairs
        decoded = slice(n, 2 * n) if separate_pairs else slice(0, n)
        other = slice(0, n) if separate_pairs else None
        assert aux_loss(changed(decoded)) != aux_loss(records)
        if other is not None:
            assert aux_loss(changed(other)) == aux_loss(records)


def test_the_contrastive_key_encoder_reads_the_pairs_spr_reads():
    model = PPOPeVFA("MlpPolicy", "Pendulum-v1", representation="spr", representation_objectives=("cl", "aux"), **FAST)
    policy = model.policy
    assert policy.representation.pairs == policy.objectives["cl"].key_encoder.pairs == slice(0, 200)
    assert policy.objectives["aux"].pairs == slice(200, 400)
