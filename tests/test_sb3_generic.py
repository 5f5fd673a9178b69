"""SB3's generic algorithm checks (save/load, predict, callbacks, determinism, spaces, dict and image
observations, train/eval mode) with PPOPeVFA in place of PPO, each on both code paths: the fast path (the default)
and SB3's own rollout (``fast_path=False``).

By design PPOPeVFA differs from SB3 PPO in its TensorBoard run name (``PPOPeVFA``) and in its ``pevfa/*`` logs;
with no representation and no history it trains exactly as SB3 PPO (``test_without_history_it_trains_as_sb3_ppo``).
"""

import gymnasium as gym
import numpy as np
import pytest
import torch as th
from conftest import AS_SB3, FAST, sb3_twin_runs
from stable_baselines3 import PPO
from stable_baselines3.common.callbacks import (
    CallbackList,
    CheckpointCallback,
    EvalCallback,
    StopTrainingOnMaxEpisodes,
    StopTrainingOnRewardThreshold,
)
from stable_baselines3.common.env_checker import check_env
from stable_baselines3.common.env_util import make_vec_env
from stable_baselines3.common.envs import (
    FakeImageEnv,
    IdentityEnv,
    IdentityEnvBox,
    IdentityEnvMultiBinary,
    IdentityEnvMultiDiscrete,
    SimpleMultiObsEnv,
)
from stable_baselines3.common.evaluation import evaluate_policy
from stable_baselines3.common.preprocessing import get_flattened_obs_dim
from stable_baselines3.common.torch_layers import BaseFeaturesExtractor
from stable_baselines3.common.utils import get_device
from stable_baselines3.common.vec_env import VecNormalize

from sb3_pevfa import REPRESENTATIONS, PPOPeVFA
from sb3_pevfa.ppo_pevfa import MlpPolicy

SPACE_ENVS = {
    "discrete": lambda: IdentityEnv(10),
    "box": lambda: IdentityEnvBox(eps=0.5),
    "multidiscrete": lambda: IdentityEnvMultiDiscrete(2),
    "multibinary": lambda: IdentityEnvMultiBinary(2),
    # a matrix-shaped Box: actions keep the action space's shape on every code path
    "box2x2": lambda: _ObservationSpaceEnv(gym.spaces.Box(-1, 1, (3,), np.float32), gym.spaces.Box(-1, 1, (2, 2), np.float32)),
}


@pytest.fixture(autouse=True, params=[True, False], ids=["fast", "sb3"])
def code_path(request, monkeypatch):
    """Every test of this file on both rollout paths (the tests build their models with ``**FAST``)."""
    monkeypatch.setitem(FAST, "fast_path", request.param)
    return request.param


TWIN_ENVS = {
    "cartpole": (lambda: make_vec_env("CartPole-v1", n_envs=1, seed=0), "MlpPolicy"),
    "pendulum-2envs-vecnormalize": (lambda: VecNormalize(make_vec_env("Pendulum-v1", n_envs=2, seed=0)), "MlpPolicy"),
    "multidiscrete": (lambda: make_vec_env(lambda: IdentityEnvMultiDiscrete(2), seed=0), "MlpPolicy"),
    "multibinary": (lambda: make_vec_env(lambda: IdentityEnvMultiBinary(2), seed=0), "MlpPolicy"),
    "box2x2": (lambda: make_vec_env(SPACE_ENVS["box2x2"], seed=0), "MlpPolicy"),
    "dict-with-image": (lambda: make_vec_env(lambda: SimpleMultiObsEnv(random_start=False), seed=0), "MultiInputPolicy"),
}


@pytest.mark.parametrize("env_name", sorted(TWIN_ENVS))
def test_without_history_it_trains_as_sb3_ppo(env_name):
    """No representation, no history, SB3's critic shape: the same weights as SB3 PPO after three updates, on every
    action and observation space, with VecNormalize and two envs."""
    make_env, policy = TWIN_ENVS[env_name]
    common = dict(n_steps=32, batch_size=16, n_epochs=2, seed=0)
    arch = dict(net_arch=dict(pi=[16], vf=[16]))
    np.random.seed(0)  # SimpleMultiObsEnv draws its observations from the global RNG when it is built
    ppo = PPO(policy, make_env(), policy_kwargs=arch, **common)
    np.random.seed(0)
    pevfa = PPOPeVFA(policy, make_env(), policy_kwargs={**arch, "critic_head_arch": []}, fast_path=FAST["fast_path"],
                     **common, **AS_SB3)  # fmt: skip
    sb3_twin_runs(ppo, pevfa, 3 * 32 * ppo.n_envs)
    if isinstance(ppo.env, VecNormalize):
        np.testing.assert_allclose(pevfa.env.obs_rms.mean, ppo.env.obs_rms.mean, rtol=1e-6)
        np.testing.assert_allclose(pevfa.env.ret_rms.var, ppo.env.ret_rms.var, rtol=1e-6)


def test_env_checker_passes_on_the_envs_of_these_tests():
    for make in (*SPACE_ENVS.values(), lambda: _ObservationSpaceEnv(gym.spaces.MultiDiscrete([3, 4]))):
        check_env(make(), warn=False)


def _saved_and_loaded(model, path):
    model.save(path)
    return PPOPeVFA.load(path, env=None)


@pytest.mark.parametrize("space", sorted(SPACE_ENVS))
@pytest.mark.parametrize("representation", REPRESENTATIONS)  # the docs' "Can I use?" table: every pair
def test_action_spaces_predict_and_save_load(tmp_path, space, representation):
    env = SPACE_ENVS[space]()
    model = PPOPeVFA("MlpPolicy", env, representation=representation, **FAST).learn(192)
    obs, _ = env.reset(seed=0)
    action, state = model.predict(obs, deterministic=True)
    assert env.action_space.contains(action) and state is None
    batch = np.stack([obs, obs])
    actions, _ = model.predict(batch, deterministic=True)
    assert actions.shape == (2, *env.action_space.shape)
    np.testing.assert_allclose(actions, np.stack([action, action]), rtol=1e-5, atol=1e-7)  # batched: round-off
    loaded = _saved_and_loaded(model, tmp_path / "model")
    np.testing.assert_array_equal(loaded.predict(batch, deterministic=True)[0], actions)
    evaluate_policy(loaded, make_vec_env(SPACE_ENVS[space], n_envs=1), n_eval_episodes=1)


def test_deterministic_predictions_and_env_none(tmp_path):
    model = PPOPeVFA("MlpPolicy", "Pendulum-v1", **FAST).learn(128)
    obs = np.stack([model.observation_space.sample() for _ in range(5)])
    first = model.predict(obs, deterministic=True)[0]
    for _ in range(3):
        np.testing.assert_array_equal(model.predict(obs, deterministic=True)[0], first)
    assert not np.array_equal(model.predict(obs, deterministic=False)[0], first)
    loaded = _saved_and_loaded(model, tmp_path / "model")
    assert loaded.env is None
    np.testing.assert_array_equal(loaded.predict(obs, deterministic=True)[0], first)
    with pytest.raises(ValueError):  # SB3's check of a wrong observation shape
        loaded.predict(np.zeros((2, 7)))


def test_callbacks(tmp_path):
    eval_env = make_vec_env("CartPole-v1", n_envs=1, seed=1)
    callbacks = CallbackList(
        [
            EvalCallback(
                eval_env,
                eval_freq=64,
                n_eval_episodes=2,
                best_model_save_path=str(tmp_path / "best"),
                log_path=str(tmp_path / "eval"),
                callback_on_new_best=StopTrainingOnRewardThreshold(reward_threshold=10_000),
            ),
            CheckpointCallback(save_freq=128, save_path=str(tmp_path / "ckpt"), name_prefix="pevfa"),
        ]
    )
    model = PPOPeVFA("MlpPolicy", "CartPole-v1", **FAST)
    model.learn(256, callback=callbacks)
    assert (tmp_path / "best" / "best_model.zip").exists() and (tmp_path / "eval" / "evaluations.npz").exists()
    checkpoint = PPOPeVFA.load(tmp_path / "ckpt" / "pevfa_128_steps")
    assert checkpoint.num_timesteps == 128
    # a stopping callback ends training early; the functional-callback form works too
    stop = StopTrainingOnMaxEpisodes(max_episodes=2)
    n_samples = model.history.n_samples
    model.learn(10_000, callback=[stop])
    assert stop.n_episodes == 2 and model.num_timesteps <= 2 * 500  # two CartPole episodes, then it stopped
    assert model.history.n_samples == n_samples + 64 * (model.num_timesteps // 64)  # an unfinished rollout is not kept
    calls = []
    model.learn(64, callback=lambda _locals, _globals: calls.append(1) or True)
    assert len(calls) == 64


@pytest.mark.parametrize("representation", ["opr", "none"])
def test_dict_observations_with_images(tmp_path, representation):
    env = SimpleMultiObsEnv(random_start=False)
    model = PPOPeVFA("MultiInputPolicy", env, representation=representation, **{**FAST, "n_steps": 32})
    model.learn(64)
    assert model.history.n_state_action_pairs == 0  # no state-action pairs with image observations
    obs, _ = env.reset()
    loaded = _saved_and_loaded(model, tmp_path / "model")
    np.testing.assert_array_equal(loaded.predict(obs, deterministic=True)[0], model.predict(obs, deterministic=True)[0])
    with pytest.raises(ValueError, match="image"):
        PPOPeVFA("MultiInputPolicy", env, representation="spr", **FAST)


@pytest.mark.parametrize("representation", [r for r in REPRESENTATIONS if r != "spr"])  # spr: no images
@pytest.mark.parametrize("discrete", [True, False])
def test_cnn_policy_encodes_the_mlp_head(tmp_path, discrete, representation):
    env = FakeImageEnv(screen_height=40, screen_width=40, n_channels=1, discrete=discrete)
    model = PPOPeVFA("CnnPolicy", env, representation=representation, **{**FAST, "n_steps": 32, "batch_size": 16})
    # default CNN architecture: no MLP between the features and the action layer, which OPR encodes alone
    n_outputs = model.action_space.n if discrete else model.action_space.shape[0]
    assert model.policy.layout.linear_shapes == ((n_outputs, 512),)
    model.learn(64)
    obs, _ = env.reset()
    loaded = _saved_and_loaded(model, tmp_path / "model")
    np.testing.assert_array_equal(loaded.predict(obs, deterministic=True)[0], model.predict(obs, deterministic=True)[0])


@pytest.mark.parametrize("rollout_encoder_gradient", [True, False])
def test_train_eval_mode(rollout_encoder_gradient):
    model = PPOPeVFA(
        "MlpPolicy", "Pendulum-v1", representation="spr", rollout_encoder_gradient=rollout_encoder_gradient, **FAST
    ).learn(128)
    policy = model.policy
    policy.set_training_mode(False)
    assert not policy.training and not policy.representation.training
    obs = th.as_tensor(np.stack([model.observation_space.sample() for _ in range(4)]))
    with th.no_grad():
        # evaluation mode: all state-action pairs are used, values are deterministic
        assert th.equal(policy.predict_values(obs), policy.predict_values(obs))
        evaluation = policy.predict_values(obs)
        policy.set_training_mode(True)
        assert policy.training and policy.representation.training
        if rollout_encoder_gradient:  # training mode: a random 80 % of the pairs at every call
            assert not th.equal(policy.predict_values(obs), policy.predict_values(obs))
        else:  # chi without gradient is the cached one, of all pairs: the rollout's values, at every call
            assert th.equal(policy.predict_values(obs), evaluation) and th.equal(policy.predict_values(obs), evaluation)


@pytest.mark.parametrize("share_features_extractor", [True, False])
def test_gsde_and_separate_features_extractor(share_features_extractor):
    model = PPOPeVFA(
        "MlpPolicy",
        "Pendulum-v1",
        use_sde=True,
        sde_sample_freq=4,
        policy_kwargs=dict(share_features_extractor=share_features_extractor, log_std_init=-1.0),
        **FAST,
    )
    # gSDE: the log-std is a matrix, flattened into the layout, last in each record
    assert model.policy.layout.log_std_shape == (64, 1)
    model.learn(128)
    assert get_device(model.device).type == "cpu"
    history = model.history
    np.testing.assert_array_equal(history.records([0])["params"][0][-64:], -1.0)  # log_std_init
    latest = history.records([history.latest_policy_id])["params"][0][-64:]
    np.testing.assert_array_equal(latest, model.policy.log_std.detach().flatten().numpy())
    assert not np.array_equal(latest, -np.ones(64))


class _ObservationSpaceEnv(gym.Env):
    """Random observations of a given space (SB3's test_spaces style)."""

    def __init__(self, observation_space, action_space=None):
        self.observation_space = observation_space
        self.action_space = gym.spaces.Discrete(2) if action_space is None else action_space

    def reset(self, seed=None, options=None):
        super().reset(seed=seed)
        if seed is not None:  # reseeding with None at every episode end would draw fresh OS entropy
            self.observation_space.seed(seed)
        return self.observation_space.sample(), {}

    def step(self, action):
        return self.observation_space.sample(), 0.0, False, bool(self.np_random.random() < 0.1), {}


@pytest.mark.parametrize(
    "observation_space",
    [
        gym.spaces.Discrete(5),
        gym.spaces.MultiDiscrete([3, 4]),
        gym.spaces.MultiBinary(3),
        gym.spaces.Box(-1, 1, (2, 3), np.float64),
    ],
)
@pytest.mark.parametrize("representation", ["opr", "spr"])
def test_observation_spaces(tmp_path, observation_space, representation):
    env = _ObservationSpaceEnv(observation_space)
    model = PPOPeVFA("MlpPolicy", env, representation=representation, **{**FAST, "n_steps": 32, "batch_size": 16})
    model.learn(96)
    obs = np.stack([observation_space.sample() for _ in range(3)])
    loaded = _saved_and_loaded(model, tmp_path / "model")
    np.testing.assert_array_equal(loaded.predict(obs, deterministic=True)[0], model.predict(obs, deterministic=True)[0])


def test_policy_save_load_and_other_number_of_envs(tmp_path):
    model = PPOPeVFA("MlpPolicy", "CartPole-v1", representation="spr", **FAST).learn(64)
    model.policy.save(tmp_path / "policy.pth")
    policy = MlpPolicy.load(tmp_path / "policy.pth")
    # like dropout, SPR subsamples its pairs in training mode: compare in evaluation mode
    policy.set_training_mode(False)
    model.policy.set_training_mode(False)
    obs = th.zeros(2, 4)
    with th.no_grad():
        assert th.equal(policy.predict_values(obs), model.policy.predict_values(obs))
    model.save(tmp_path / "model")
    model.save_history(tmp_path / "history")
    # as in SB3, a model is loaded with another number of envs through load(path, env)
    more_envs = PPOPeVFA.load(tmp_path / "model", env=make_vec_env("CartPole-v1", n_envs=2))
    more_envs.load_history(tmp_path / "history")
    more_envs.learn(128, reset_num_timesteps=False)
    assert more_envs.history.n_samples == 64 + 128


@pytest.mark.parametrize("representation", ["opr", "spr", "random", "none"])
def test_get_set_parameters_as_sb3_checks_them(tmp_path, representation):
    """SB3's save/load contract: every state-dict entry can be randomised and set, errors on bad input, round trip."""
    objectives = ("cl", "aux") if representation in ("opr", "spr") else ()
    model = PPOPeVFA(
        "MlpPolicy",
        IdentityEnvBox(-10, 10),
        representation=representation,
        representation_objectives=objectives,
        policy_kwargs=dict(net_arch=[16]),
        **{**FAST, "n_steps": 64},
    ).learn(128)
    original = {
        name: {k: v.clone() for k, v in sd.items()} if "optim" not in name else sd
        for name, sd in model.get_parameters().items()
    }
    with pytest.raises(ValueError):
        model.set_parameters({**original, "not_an_object": {}}, exact_match=True)
    with pytest.raises(ValueError):
        model.set_parameters(dict(list(original.items())[:-1]), exact_match=True)
    with pytest.raises(RuntimeError):
        model.set_parameters({name: dict(list(sd.items())[:-1]) for name, sd in original.items()}, exact_match=True)
    randomised = {
        name: sd if "optim" in name else {k: th.rand_like(v) for k, v in list(sd.items())[:-1]}
        for name, sd in original.items()
    }
    model.set_parameters(randomised, exact_match=False)
    new = model.get_parameters()
    for name, sd in original.items():
        if "optim" in name:
            continue
        *changed, last = sd
        assert th.equal(sd[last], new[name][last])
        assert all(not th.allclose(sd[k], new[name][k]) for k in changed), name
    obs = np.stack([model.observation_space.sample() for _ in range(5)])
    actions = model.predict(obs, deterministic=True)[0]
    model.save(tmp_path / "model")
    for device in ("auto", "cpu"):
        loaded = PPOPeVFA.load(tmp_path / "model", env=make_vec_env(lambda: IdentityEnvBox(-10, 10)), device=device)
        np.testing.assert_allclose(loaded.predict(obs, deterministic=True)[0], actions, rtol=1e-4)
        loaded.learn(64)
    # SB3's load with custom objects and system info
    custom = PPOPeVFA.load(tmp_path / "model", custom_objects=dict(learning_rate=2e-5, dummy=1.0), print_system_info=True)
    assert custom.learning_rate == 2e-5 and not hasattr(custom, "dummy")


class _BatchNormDropoutExtractor(BaseFeaturesExtractor):
    """Flatten, batch norm and dropout: train/eval mode matters (SB3's test_train_eval_mode style)."""

    def __init__(self, observation_space):
        super().__init__(observation_space, get_flattened_obs_dim(observation_space))
        self.layers = th.nn.Sequential(th.nn.Flatten(), th.nn.BatchNorm1d(self.features_dim), th.nn.Dropout(0.5))

    def forward(self, observations):
        return self.layers(observations)


@pytest.mark.parametrize("env_id", ["CartPole-v1", "Pendulum-v1"])
def test_batch_norm_and_dropout_follow_train_eval_mode(env_id):
    policy_kwargs = dict(net_arch=[16, 16], features_extractor_class=_BatchNormDropoutExtractor)
    model = PPOPeVFA("MlpPolicy", env_id, policy_kwargs=policy_kwargs, **FAST)
    batch_norm = model.policy.features_extractor.layers[1]
    before = batch_norm.running_mean.clone()
    # rollouts (and the policy records taken at their start) run in evaluation mode
    _, callback = model._setup_learn(128)
    for _ in range(2):
        model.collect_rollouts(model.get_env(), callback, model.rollout_buffer, n_rollout_steps=model.n_steps)
    assert th.equal(batch_norm.running_mean, before)
    obs = model.get_env().reset()
    first = model.predict(obs, deterministic=True)[0]
    assert all(np.array_equal(model.predict(obs, deterministic=True)[0], first) for _ in range(5))
    model.learn(128)
    assert not th.allclose(batch_norm.running_mean, before)


@pytest.mark.parametrize("representation", ["opr", "spr"])
def test_mixed_dict_observations_with_objectives(tmp_path, representation):
    model = PPOPeVFA(
        "MultiInputPolicy",
        # Dict observations with discrete, box and binary keys; MultiDiscrete actions
        _ObservationSpaceEnv(
            gym.spaces.Dict({"d": gym.spaces.Discrete(3), "b": gym.spaces.Box(-1, 1, (2,)), "m": gym.spaces.MultiBinary(2)}),
            gym.spaces.MultiDiscrete([2, 3]),
        ),
        representation=representation,
        representation_objectives=("cl", "aux"),
        objective_kwargs={"cl": {"learning_starts": 0}, "aux": {"learning_starts": 0}},
        **FAST,
    )
    model.learn(192)
    # states are flattened after preprocessing (keys in sorted order): box(2) + one-hot(3) + binary(2); with SPR the
    # AUX objective decodes 200 pairs of its own
    assert model.history.records([0])["states"].shape == (1, 400 if representation == "spr" else 200, 7)
    states = model.history.records(model.history.policy_ids)["states"]
    np.testing.assert_array_equal(states[..., 2:5].sum(-1), 1)  # the one-hot of the Discrete key
    assert np.isin(states[..., 2:], [0, 1]).all() and (np.abs(states[..., :2]) <= 1).all()
    obs = {key: np.stack([space.sample() for _ in range(3)]) for key, space in model.observation_space.spaces.items()}
    loaded = _saved_and_loaded(model, tmp_path / "model")
    np.testing.assert_array_equal(loaded.predict(obs, deterministic=True)[0], model.predict(obs, deterministic=True)[0])


@pytest.mark.parametrize("representation", ["opr", "none"])
def test_critic_only_steps_leave_a_shared_cnn_extractor_and_the_actor_alone(representation):
    """History and critic-first steps train the critic alone: with a features extractor shared by actor and critic
    (SB3's CnnPolicy default) the actor's outputs stay exactly as they were, so the rollout's log-probabilities
    stay valid for the PPO update."""
    env = FakeImageEnv(screen_height=36, screen_width=36, n_channels=1, discrete=True)
    model = PPOPeVFA("CnnPolicy", env, representation=representation, update_order="critic_first",
                     **{**FAST, "n_steps": 32, "batch_size": 16})  # fmt: skip
    assert model.policy.share_features_extractor
    model.learn(96)
    obs = th.as_tensor(np.stack([model.observation_space.sample() for _ in range(4)]))

    def actor_outputs():
        with th.no_grad():
            return model.policy.get_distribution(obs).distribution.logits.clone()

    def critic():
        return th.cat([p.detach().flatten().clone() for p in model.policy.critic_parameters()])

    before, extractor = actor_outputs(), [p.detach().clone() for p in model.policy.features_extractor.parameters()]
    critic_before = critic()
    model._history_credit = 4 * model.history_train_freq
    assert len(model._train_on_history()) == 6  # credit 4 * 16 plus one rollout's 32 steps, one step per 16
    model._train_critic_on_rollout()
    assert not th.equal(critic(), critic_before)  # the critic did train
    assert th.equal(actor_outputs(), before)
    assert all(th.equal(a, b) for a, b in zip(model.policy.features_extractor.parameters(), extractor))


@pytest.mark.parametrize("algorithm", ["ppo_pevfa", "sac_pevfa", "td3_pevfa"])
def test_load_takes_the_policy_kwargs_the_constructor_took(tmp_path, algorithm):
    import io

    from sb3_pevfa import SACPeVFA, TD3PeVFA

    cls, env_id = {"ppo_pevfa": (PPOPeVFA, "CartPole-v1"), "sac_pevfa": (SACPeVFA, "Pendulum-v1"),
                   "td3_pevfa": (TD3PeVFA, "Pendulum-v1")}[algorithm]  # fmt: skip
    model = cls("MlpPolicy", env_id, policy_kwargs=dict(net_arch=[16, 16]), representation="random", embedding_dim=8)
    model.save(tmp_path / "model.zip")
    loaded = cls.load(tmp_path / "model.zip", policy_kwargs=dict(net_arch=[16, 16]))  # as SB3's PPO / TD3 load it
    assert loaded.policy_kwargs == model.policy_kwargs
    stream = io.BytesIO((tmp_path / "model.zip").read_bytes())
    assert cls.load(stream, policy_kwargs=dict(net_arch=[16, 16])).policy_kwargs == model.policy_kwargs
    with pytest.raises(ValueError, match="policy kwargs do not equal the stored"):  # SB3's check of a real difference
        cls.load(tmp_path / "model.zip", policy_kwargs=dict(net_arch=[16, 16], embedding_dim=4))
    with pytest.raises(ValueError, match="policy kwargs do not equal the stored"):
        cls.load(tmp_path / "model.zip", policy_kwargs=dict(net_arch=[8]))
    with pytest.raises(ValueError, match="policy kwargs do not equal the stored"):  # a PeVFA argument of load's
        cls.load(tmp_path / "model.zip", policy_kwargs=dict(net_arch=[16, 16]), embedding_dim=4)
    with pytest.raises(ValueError, match="load got representation='opr', the file's policy was built with 'random'"):
        cls.load(tmp_path / "model.zip", representation="opr")  # alone (rl-zoo3's -i), not kept unread
    assert cls.load(tmp_path / "model.zip", representation="random", embedding_dim=8).policy_kwargs == model.policy_kwargs
    if cls is PPOPeVFA:  # the critic's entries a constructor would have added by default are not the stored ones
        other = cls("MlpPolicy", env_id, policy_kwargs=dict(net_arch=[16, 16], chi_normalization="none"))
        other.save(tmp_path / "other")
        with pytest.raises(ValueError, match="policy kwargs do not equal the stored"):
            cls.load(tmp_path / "other", policy_kwargs=dict(net_arch=[16, 16]))
        assert cls.load(tmp_path / "other", policy_kwargs=dict(net_arch=[16, 16], chi_normalization="none"))


@pytest.mark.parametrize("algorithm", ["ppo_pevfa", "sac_pevfa"])
def test_a_failed_save_leaves_the_previous_model_file_as_it_was(tmp_path, monkeypatch, algorithm):
    """SB3 writes the zip in place: a save that fails half way would leave a broken file where a good one was."""
    import stable_baselines3.common.base_class as base_class

    from sb3_pevfa import SACPeVFA

    cls = {"ppo_pevfa": PPOPeVFA, "sac_pevfa": SACPeVFA}[algorithm]
    model = cls("MlpPolicy", "Pendulum-v1", policy_kwargs=dict(net_arch=[16]), seed=0)
    model.save(tmp_path / "model")  # SB3 adds .zip
    before = (tmp_path / "model.zip").read_bytes()
    written = base_class.save_to_zip_file

    def fails(path, **kwargs):
        written(path, **kwargs)
        with open(path, "r+b") as handle:  # the file cut short, then the error
            handle.truncate(100)
        raise OSError("No space left on device")

    monkeypatch.setattr(base_class, "save_to_zip_file", fails)
    with th.no_grad():
        next(model.policy.parameters()).add_(1.0)
    with pytest.raises(OSError, match="No space left"):
        model.save(tmp_path / "model")
    assert [path.name for path in tmp_path.iterdir()] == ["model.zip"] and (tmp_path / "model.zip").read_bytes() == before
    monkeypatch.undo()
    model.save(str(tmp_path / "model"))
    assert (tmp_path / "model.zip").read_bytes() != before
    th.testing.assert_close(cls.load(tmp_path / "model").policy.state_dict(), model.policy.state_dict())


def test_a_model_saved_again_keeps_its_files_permissions_and_link(tmp_path):
    """Written beside and renamed over it, as SB3's write in place would leave them: the link's target is replaced."""
    import os
    import stat

    model = PPOPeVFA("MlpPolicy", "CartPole-v1", policy_kwargs=dict(net_arch=[8]))
    (tmp_path / "runs").mkdir()
    model.save(tmp_path / "runs" / "model.zip")
    os.chmod(tmp_path / "runs" / "model.zip", 0o640)
    (tmp_path / "latest.zip").symlink_to(tmp_path / "runs" / "model.zip")
    with th.no_grad():
        next(model.policy.parameters()).add_(1.0)
    model.save(tmp_path / "latest")  # SB3 adds .zip: the link
    assert (tmp_path / "latest.zip").is_symlink() and sorted(p.name for p in (tmp_path / "runs").iterdir()) == ["model.zip"]
    assert stat.S_IMODE(os.stat(tmp_path / "runs" / "model.zip").st_mode) == 0o640
    th.testing.assert_close(PPOPeVFA.load(tmp_path / "runs" / "model.zip").policy.state_dict(), model.policy.state_dict())


@pytest.mark.parametrize("algorithm", ["ppo_pevfa", "a2c_pevfa", "sac_pevfa", "td3_pevfa"])
def test_load_refuses_another_algorithms_file_and_settings_the_constructor_refuses(tmp_path, algorithm):
    """A clear error at load, before anything trains: a file of another algorithm (or SB3's own class) names the
    policy it needs; the arguments given to load are checked as the constructor checks them."""
    from stable_baselines3 import A2C, PPO, SAC, TD3

    from sb3_pevfa import A2CPeVFA, SACPeVFA, TD3PeVFA

    cls, sb3, bad, message = {
        "ppo_pevfa": (PPOPeVFA, PPO, dict(history_train_freq=-1), "history_train_freq must be an int >= 0"),
        "a2c_pevfa": (A2CPeVFA, A2C, dict(history_batch_size=0), "history_batch_size must be a positive int"),
        "sac_pevfa": (SACPeVFA, SAC, dict(snapshot_freq=2.5), "snapshot_freq must be an int >= 1"),
        "td3_pevfa": (TD3PeVFA, TD3, dict(history_batch_size=500), "must be a multiple of history_batch_policies"),
    }[algorithm]
    for other in {PPOPeVFA, A2CPeVFA, SACPeVFA, TD3PeVFA, sb3} - {cls}:
        other("MlpPolicy", "Pendulum-v1", policy_kwargs=dict(net_arch=[16])).save(tmp_path / other.__name__)
        # a PeVFA file names the SB3 algorithm of its class (PPOPeVFA's and A2CPeVFA's share a policy class); SB3's own
        # file is refused by its policy
        refusal = rf"{cls.__name__} needs its PeVFA policy" if other is sb3 else "holds a model of an algorithm based on"
        for entry in ({}, dict(representation="opr", embedding_dim=64)):  # rl-zoo3's -i passes its entry's arguments
            with pytest.raises(TypeError, match=refusal):
                cls.load(tmp_path / other.__name__, **entry)
    cls("MlpPolicy", "Pendulum-v1", policy_kwargs=dict(net_arch=[16])).save(tmp_path / "mine")
    with pytest.raises(ValueError, match=message):
        cls.load(tmp_path / "mine", **bad)
    with pytest.raises((ValueError, TypeError), match="flush_denormal must be a bool"):
        cls.load(tmp_path / "mine", flush_denormal=1)
    if cls is PPOPeVFA:  # its own argument too
        with pytest.raises(ValueError, match="actor_batch_size must be None, an int > 1 or 'full', got 0"):
            cls.load(tmp_path / "mine", actor_batch_size=0)
    with pytest.raises(TypeError, match=r"\(SB3's own policy; a file saved by SB3's algorithm loads with that algorithm"):
        cls.load(tmp_path / sb3.__name__)


@pytest.mark.parametrize("algorithm", ["ppo_pevfa", "a2c_pevfa", "sac_pevfa", "td3_pevfa"])
def test_a_misspelt_argument_and_a_missing_env_are_named(tmp_path, algorithm):
    """SB3's load sets any keyword argument on the model, and its learn asserts an env without a message: here a
    misspelt argument of load or of the constructor is a TypeError that suggests the name meant, and learn without an
    env says how to give one."""
    from sb3_pevfa import A2CPeVFA, SACPeVFA, TD3PeVFA

    cls = {"ppo_pevfa": PPOPeVFA, "a2c_pevfa": A2CPeVFA, "sac_pevfa": SACPeVFA, "td3_pevfa": TD3PeVFA}[algorithm]
    with pytest.raises(TypeError, match=rf"{cls.__name__}.* got an unexpected keyword argument 'learning_rat'"):
        cls("MlpPolicy", "Pendulum-v1", learning_rat=0.1)
    model = cls("MlpPolicy", make_vec_env("Pendulum-v1", n_envs=1), policy_kwargs=dict(net_arch=[16]))
    model.save(tmp_path / "model")
    typo = "history_train_frq"
    with pytest.raises(TypeError, match=rf"{cls.__name__}.load\(\) got .* '{typo}'; did you mean 'history_train_freq'"):
        cls.load(tmp_path / "model", **{typo: 2})
    with pytest.raises(TypeError, match=r"load\(\) got an unexpected keyword argument 'restore_rng'; did you mean "
                       r"'restore_rng_state'\?"):  # fmt: skip
        cls.load(tmp_path / "model", restore_rng=True)
    refused = rf"^{cls.__name__}.load\(\) takes an env, not the id 'Pendulum-v1' .*: pass make_vec_env\('Pendulum-v1'\) or"
    for given in (dict(env="Pendulum-v1"), {}):  # an id, by keyword or in SB3's place of the env
        with pytest.raises(ValueError, match=refused + r" gymnasium.make\('Pendulum-v1'\), or env=None$"):
            cls.load(tmp_path / "model", *([] if given else ["Pendulum-v1"]), **given)
    loaded = cls.load(tmp_path / "model", history_train_freq=2, seed=3, device="cpu", force_reset=False)
    assert loaded.history_train_freq == 2 and loaded.seed == 3  # the constructor's arguments, SB3's load's
    with pytest.raises(ValueError, match=rf"{cls.__name__} has no env to learn on .* pass env= to load\(\)"):
        loaded.learn(10)
    assert ("samples=" in repr(loaded.history)) == (cls in (PPOPeVFA, A2CPeVFA))  # off-policy: records only
