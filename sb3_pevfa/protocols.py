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
"""

import copy
import math
from typing import Any

from torch import nn

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


def paper_protocol(algorithm: str = "ppo_pevfa", **overrides: Any) -> dict[str, Any]:
    """The constructor arguments of :class:`~sb3_pevfa.PPOPeVFA` for the paper's ``algorithm`` (``"ppo"`` or
    ``"ppo_pevfa"``), with ``overrides`` on top (``policy_kwargs`` merged key by key), e.g.
    ``paper_protocol("ppo_pevfa", representation="spr")``."""
    if algorithm not in PAPER_ALGORITHMS:
        raise ValueError(f"Unknown algorithm {algorithm!r} of the paper's protocol, valid choices: {sorted(PAPER_ALGORITHMS)}")
    arguments = {**PAPER_COMMON, **copy.deepcopy(PAPER_ALGORITHMS[algorithm])}
    policy_kwargs = {**PAPER_ACTOR, **arguments.pop("policy_kwargs"), **(overrides.pop("policy_kwargs", None) or {})}
    return {**arguments, **overrides, "policy_kwargs": policy_kwargs}


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
