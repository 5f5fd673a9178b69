"""Named training protocols: the paper's (Appendix F.1, Tables 2 and 3) for PPO-PeVFA and for its PPO baseline.

The paper trains both algorithms without code-level optimizations (no observation normalization, no reward
scaling, no gradient clipping, no parameters shared by actor and critic), with separate learning rates, the critic
updated first on Monte-Carlo returns, and the actor then updated with advantages from the updated critic. SB3's
``PPO`` cannot express that baseline (one learning rate, a joint update, TD(lambda) targets), so both are built from
:class:`~sb3_pevfa.PPOPeVFA`: the baseline is its conventional critic (``representation="none"``, no historical
updates, a history of the current policy only).

    from sb3_pevfa.protocols import paper_protocol
    model = PPOPeVFA("MlpPolicy", "Hopper-v5", **paper_protocol("ppo_pevfa"), seed=0)   # PPO-PeVFA, OPR, E2E
    model = PPOPeVFA("MlpPolicy", "Hopper-v5", **paper_protocol("ppo"), seed=0)         # the paper's PPO

Where the paper is silent, or SB3's policy classes differ from its networks: :data:`PAPER_DEVIATIONS`.

The authors' protocol (:func:`authors_protocol`, :func:`make_authors_env`) is their public code's training loop
(TJU-DRL-LAB/self-supervised-rl, PPO-PeVFA, TensorFlow 1), each of its mechanics an option of the classes:
iterations of whole episodes, a time feature, no bootstrap anywhere, a tanh mean, 10 full-batch actor steps per
iteration, N(0, 1/fan_in) weights. Where it differs from their code: :data:`AUTHORS_DEVIATIONS`.

    from sb3_pevfa.protocols import authors_protocol, make_authors_env
    model = PPOPeVFA("MlpPolicy", make_authors_env("Hopper-v5", seed=0), **authors_protocol("ppo_pevfa"), seed=0)
"""

import copy
import math
from typing import Any

import gymnasium as gym
import numpy as np
from stable_baselines3.common.env_util import make_vec_env
from stable_baselines3.common.vec_env import VecEnv
from torch import nn

from sb3_pevfa.envs.time_feature import ElapsedTimeFeatureWrapper
from sb3_pevfa.pevfa.arguments import PAPER_SCHEDULE

#: Table 2: what PPO and PPO-PeVFA share (``max_grad_norm=inf``: no gradient clipping)
PAPER_COMMON: dict[str, Any] = dict(
    learning_rate=1e-4,
    critic_learning_rate=1e-3,
    n_steps=2000,
    batch_size=128,
    n_epochs=10,
    gamma=0.99,
    gae_lambda=0.95,
    clip_range=0.2,
    ent_coef=0.0,
    max_grad_norm=math.inf,
    update_order="critic_first",
    value_target_lambda=1.0,
)
#: The actor of both: 2x64 ReLU, Gaussian with a state-independent log-std, PyTorch's default initialization
PAPER_ACTOR: dict[str, Any] = dict(activation_fn=nn.ReLU, ortho_init=False, log_std_init=0.0)
#: PPO-PeVFA (Table 3, Fig. 7): state -> 64 and chi (64) -> 64, concatenated -> 128 -> 1, all ReLU; OPR trained end
#: to end; one historical update of 64 uniform samples per 10 environment steps from a 200k-sample FIFO after 5k steps
PAPER_PEVFA: dict[str, Any] = dict(
    representation="opr",
    embedding_dim=64,
    history_buffer_size=200_000,
    history_learning_starts=5_000,
    **PAPER_SCHEDULE,
    policy_kwargs=dict(
        net_arch=dict(pi=[64, 64], vf=[64]),
        critic_embedding_arch=[64],
        critic_head_arch=[128],
        critic_activation_fn=nn.ReLU,
        chi_normalization="none",
    ),
)
#: The paper's PPO: a conventional 2x128 ReLU critic (no chi input, no historical updates, no representation
#: parameters); the history holds the current policy only, the record its values are computed for
PAPER_PPO: dict[str, Any] = dict(
    representation="none",
    history_train_freq=0,
    n_state_action_pairs=0,
    history_buffer_size=PAPER_COMMON["n_steps"],
    history_max_policies=1,
    policy_kwargs=dict(net_arch=dict(pi=[64, 64], vf=[128]), critic_head_arch=[128], critic_activation_fn=nn.ReLU),
)
#: Valid algorithms of :func:`paper_protocol`
PAPER_ALGORITHMS = {"ppo": PAPER_PPO, "ppo_pevfa": PAPER_PEVFA}


def _arguments(
    name: str, common: dict[str, Any], actor: dict[str, Any], algorithms: dict[str, dict[str, Any]], algorithm: str,
    overrides: dict[str, Any],
) -> dict[str, Any]:  # fmt: skip
    if algorithm not in algorithms:
        raise ValueError(f"Unknown algorithm {algorithm!r} of the {name} protocol, valid choices: {sorted(algorithms)}")
    arguments = {**common, **copy.deepcopy(algorithms[algorithm])}
    policy_kwargs = {**actor, **arguments.pop("policy_kwargs"), **(overrides.pop("policy_kwargs", None) or {})}
    return {**arguments, **overrides, "policy_kwargs": policy_kwargs}


def paper_protocol(algorithm: str = "ppo_pevfa", **overrides: Any) -> dict[str, Any]:
    """The constructor arguments of :class:`~sb3_pevfa.PPOPeVFA` for the paper's ``algorithm`` (``"ppo"`` or
    ``"ppo_pevfa"``), with ``overrides`` on top (``policy_kwargs`` merged key by key), e.g.
    ``paper_protocol("ppo_pevfa", representation="spr")``."""
    return _arguments("paper's", PAPER_COMMON, PAPER_ACTOR, PAPER_ALGORITHMS, algorithm, overrides)


#: How this package's paper protocol, and the campaign that runs it (``benchmarks/campaign.py``), differ from the
#: paper's runs
PAPER_DEVIATIONS = (
    "Tasks: Gymnasium's -v5 MuJoCo tasks and LunarLanderContinuous-v3 (the paper: gym 0.9.1's -v1 on mujoco-py 0.5.4, "
    "LunarLander-v2); absolute returns do not compare, ratios to each one's PPO do.",
    "1M env steps per run (the paper: 2M, 4M on Ant); 5 seeds until seeds 5-9 run (the paper: 10).",
    "The Gaussian's mean is linear, not tanh-activated (SB3's policy classes); SB3 clips actions to the Box.",
    "Iterations of exactly 2000 steps (the paper: 5 episodes or 2000 steps), in minibatches of 128, the last of 80.",
    "Where the paper is silent, SB3's choices: advantages normalized per minibatch, Adam's epsilon 1e-5; and "
    "PyTorch's default initialization (no orthogonal one).",
    "Monte-Carlo targets are bootstrapped with the critic where the rollout cuts an episode or a time limit ends it.",
    "Evaluation every 20k steps: 10 deterministic episodes on an env seeded with the run's seed + 10000; max average "
    "return = the best evaluation.",
)


#: The authors' code (``networks/ppo.py``, ``mujoco_run_ppo_epoch.py``): what PPO and PPO-PeVFA share
AUTHORS_COMMON: dict[str, Any] = dict(
    **PAPER_COMMON,
    # an iteration: 5 whole episodes of one env, or fewer once 2000 steps were collected (the episode finished)
    rollout_episodes=5,
    # discounted Monte-Carlo returns, never bootstrapped: episodes capped at 1000 steps end as terminal ones
    bootstrap_truncated=False,
    # the log-probabilities of the actions the env received (clipped to [-1, 1])
    train_on_clipped_actions=True,
    # critic first: 10 epochs of N // (N // 128) samples, the remainder left out; then 10 full-batch actor steps
    critic_minibatches="even",
    actor_batch_size="full",
)
#: Their actor: 2x64 ReLU, a tanh mean, a log-variance of 13 trainable rows (0) summed, - 1: std e^-0.5 at the start,
#: as one log-std at 6.5x the actor's Adam rate; every weight N(0, 1/fan_in), biases 0; TensorFlow's Adam (eps 1e-8)
AUTHORS_ACTOR: dict[str, Any] = dict(
    activation_fn=nn.ReLU,
    ortho_init=False,
    log_std_init=-0.5,
    mean_activation_fn=nn.Tanh,
    log_std_lr_scale=6.5,
    weight_init="normal_fan_in",
    optimizer_kwargs=dict(eps=1e-8, fused=True),
)
#: Their PPO: a 2x128 ReLU V(s); their PPO-PeVFA (``mujoco_run_ppo_pevf_e2e_opr_Sep.py``): the paper's, OPR trained
#: end to end by the on-policy and the historical fits through one Adam
AUTHORS_ALGORITHMS = {"ppo": PAPER_PPO, "ppo_pevfa": PAPER_PEVFA}
#: Episodes of the authors' protocol end after this many steps (their ``MAX_EP_STEPS``); the time feature is t / this
AUTHORS_MAX_EPISODE_STEPS = 1000


def authors_protocol(algorithm: str = "ppo_pevfa", **overrides: Any) -> dict[str, Any]:
    """The constructor arguments of :class:`~sb3_pevfa.PPOPeVFA` for ``algorithm`` (``"ppo"`` or ``"ppo_pevfa"``) as
    the authors' code trains it, with ``overrides`` on top (``policy_kwargs`` merged key by key). Train on an env of
    :func:`make_authors_env` (the time feature, the episode cap and actions in [-1, 1])."""
    return _arguments("authors'", AUTHORS_COMMON, AUTHORS_ACTOR, AUTHORS_ALGORITHMS, algorithm, overrides)


def authors_env(env_id: str, **kwargs: Any) -> gym.Env:
    """One env of the authors' protocol: episodes capped at 1000 steps, actions in [-1, 1] scaled to the bounds,
    t / 1000 appended to the observation (:class:`~sb3_pevfa.envs.time_feature.ElapsedTimeFeatureWrapper`)."""
    env = gym.make(env_id, max_episode_steps=AUTHORS_MAX_EPISODE_STEPS, **kwargs)
    space = env.action_space
    if isinstance(space, gym.spaces.Box) and not (np.all(space.low == -1.0) and np.all(space.high == 1.0)):
        env = gym.wrappers.RescaleAction(env, -1.0, 1.0)
    return ElapsedTimeFeatureWrapper(env, max_steps=AUTHORS_MAX_EPISODE_STEPS)


def make_authors_env(env_id: str, seed: int | None = None) -> VecEnv:
    """SB3's ``make_vec_env`` of one :func:`authors_env` (with SB3's ``Monitor``), seeded with ``seed``."""
    return make_vec_env(authors_env, n_envs=1, seed=seed, env_kwargs=dict(env_id=env_id))


#: How this package's authors' protocol, and the campaign that runs it (``benchmarks/campaign.py``), differ from the
#: authors' code
AUTHORS_DEVIATIONS = (
    "Tasks: Gymnasium's -v5 MuJoCo tasks and LunarLanderContinuous-v3 (their code: gym's -v1 tasks, LunarLander-v2).",
    "2M env steps on every task, Ant included (the paper: 4M on Ant; their code has no Ant setting); seeds 0-4.",
    "Their log-variance is 13 trainable rows summed, - 1; here one log-std (initial -0.5) whose Adam learning rate is "
    "6.5x the actor's: the same steps up to Adam's epsilon. OPR reads that log-std, not the 13 rows.",
    "The critic's loss is the MSE, theirs 0.5 * MSE: the same Adam steps up to its epsilon.",
    "SB3's Adam (eps 1e-8 added after the bias correction; TensorFlow 1 adds it before) and SB3's advantage "
    "normalization (std + 1e-8; theirs + 1e-6).",
    "Evaluation every 20k steps: 10 episodes with sampled actions on an env seeded with the run's seed + 10000, the "
    "first at 20k (theirs also at step 1); max average return = the best evaluation.",
    "Their OPR encoder's first layer of the log-variance block starts with std sqrt(a_dim / 13) (an operator "
    "precedence slip); here N(0, 1/fan_in) like every other layer.",
)
