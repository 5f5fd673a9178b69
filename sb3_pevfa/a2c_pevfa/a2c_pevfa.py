"""A2C with a Policy-extended Value Function Approximator: SB3's A2C with PPOPeVFA's critic, history and objectives."""

from typing import Any, ClassVar

import torch as th
from stable_baselines3 import A2C
from stable_baselines3.common.buffers import RolloutBuffer
from stable_baselines3.common.policies import BasePolicy
from stable_baselines3.common.type_aliases import GymEnv, Schedule

from sb3_pevfa.a2c_pevfa.policies import CnnPolicy, MlpPolicy, MultiInputPolicy, PeVFAActorCriticPolicy
from sb3_pevfa.pevfa.algorithm import PeVFAAlgorithm
from sb3_pevfa.pevfa.arguments import PEVFA_ARGUMENTS, action_space_errors_as_type_errors, pevfa_policy_kwargs


class A2CPeVFA(PeVFAAlgorithm, A2C):
    """A2C whose critic is a PeVFA V(s, chi_pi), trained on the data of all historical policies.

    The iteration of :class:`~sb3_pevfa.PPOPeVFA` (:meth:`~sb3_pevfa.pevfa.algorithm.PeVFAAlgorithm.train`) with
    SB3's A2C update in place of PPO's: one gradient step on the whole rollout. In the ``critic_first`` order the
    critic takes one step on the rollout, advantages are recomputed, then the actor takes its step.

    A2C updates every ``n_steps * n_envs`` environment steps (5 by default), and every update is a new policy in
    the history: the history holds up to ``history_max_policies`` records and their samples.

    Parameters not listed are SB3 A2C's (:class:`~stable_baselines3.A2C`); the PeVFA parameters (``representation``
    to ``critic_minibatches``) are PPOPeVFA's (:class:`~sb3_pevfa.PPOPeVFA`). ``fast_path`` batches the critic's values
    after each rollout; A2C's own update is used on both paths. A2CPeVFA's default schedule of historical updates is one
    batch of 256 samples of 8 policies per 200 env steps, the encoder trained by them alone
    (``rollout_encoder_gradient=None``): A2C updates every few env steps, and the paper's schedule
    (:data:`~sb3_pevfa.PAPER_SCHEDULE`: 64 samples per 10 steps, the encoder also trained on every rollout) made it
    about 5x slower than A2C in rl-zoo3's CartPole-v1 settings; this one costs about 1.4x A2C's CPU time there
    (``benchmarks/speed_zoo.py --setting a2c-cartpole``; docs/notes/2026-12-05-a2c-default-schedule.md). The CL
    objective steps on the same cadence unless its own ``train_freq`` is given (AUX: every 10 env steps by default).
    """

    policy_aliases: ClassVar[dict[str, type[BasePolicy]]] = {
        "MlpPolicy": MlpPolicy,
        "CnnPolicy": CnnPolicy,
        "MultiInputPolicy": MultiInputPolicy,
    }
    policy: PeVFAActorCriticPolicy

    def __init__(
        self,
        policy: str | type[PeVFAActorCriticPolicy],
        env: GymEnv | str,
        learning_rate: float | Schedule = 7e-4,
        n_steps: int = 5,
        gamma: float = 0.99,
        gae_lambda: float = 1.0,
        ent_coef: float = 0.0,
        vf_coef: float = 0.5,
        max_grad_norm: float = 0.5,
        rms_prop_eps: float = 1e-5,
        use_rms_prop: bool = True,
        use_sde: bool = False,
        sde_sample_freq: int = -1,
        rollout_buffer_class: type[RolloutBuffer] | None = None,
        rollout_buffer_kwargs: dict[str, Any] | None = None,
        normalize_advantage: bool = False,
        stats_window_size: int = 100,
        tensorboard_log: str | None = None,
        representation: str = "opr",
        embedding_dim: int = 64,
        representation_kwargs: dict[str, Any] | None = None,
        n_state_action_pairs: int = 200,
        representation_objectives: tuple[str, ...] | list[str] = (),
        objective_kwargs: dict[str, dict[str, Any]] | None = None,
        critic_learning_rate: float | Schedule | None = None,
        update_order: str = "joint",
        value_target_lambda: float | None = None,
        history_buffer_size: int = 200_000,
        history_max_policies: int = 10_000,
        history_batch_size: int = 256,
        history_batch_policies: int | None = 8,
        history_train_freq: int = 200,
        history_learning_starts: int = 5_000,
        history_targets: str = "rollout",
        history_target_refresh: int = 1,
        history_normalization: str = "current",
        rollout_encoder_gradient: bool | None = None,
        fast_path: bool = True,
        flush_denormal: bool = True,
        rollout_episodes: int | None = None,
        bootstrap_truncated: bool = True,
        train_on_clipped_actions: bool = False,
        critic_minibatches: str = "sb3",
        policy_kwargs: dict[str, Any] | None = None,
        verbose: int = 0,
        seed: int | None = None,
        device: th.device | str = "auto",
        _init_setup_model: bool = True,
    ):
        pevfa = {name: value for name, value in locals().items() if name in PEVFA_ARGUMENTS}
        with action_space_errors_as_type_errors():
            super().__init__(
                policy,
                env,
                learning_rate=learning_rate,
                n_steps=n_steps,
                gamma=gamma,
                gae_lambda=gae_lambda,
                ent_coef=ent_coef,
                vf_coef=vf_coef,
                max_grad_norm=max_grad_norm,
                rms_prop_eps=rms_prop_eps,
                use_rms_prop=use_rms_prop,
                use_sde=use_sde,
                sde_sample_freq=sde_sample_freq,
                rollout_buffer_class=rollout_buffer_class,
                rollout_buffer_kwargs=rollout_buffer_kwargs,
                normalize_advantage=normalize_advantage,
                stats_window_size=stats_window_size,
                tensorboard_log=tensorboard_log,
                policy_kwargs=pevfa_policy_kwargs(policy_kwargs, pevfa),
                verbose=verbose,
                seed=seed,
                device=device,
                _init_setup_model=False,
            )
        self._init_pevfa(env, pevfa)
        if _init_setup_model:
            self._setup_model()

    def _rollout_critic_schedule(self) -> tuple[int, int]:
        return 1, self._rollout_size()
