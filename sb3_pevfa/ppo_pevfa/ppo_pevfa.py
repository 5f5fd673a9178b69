"""PPO with a Policy-extended Value Function Approximator (PPO-PeVFA, paper Algorithm 2)."""

import warnings
from typing import Any, ClassVar

import torch as th
from stable_baselines3 import PPO
from stable_baselines3.common.buffers import RolloutBuffer
from stable_baselines3.common.policies import BasePolicy
from stable_baselines3.common.type_aliases import GymEnv, Schedule

from sb3_pevfa.pevfa.algorithm import PeVFAAlgorithm
from sb3_pevfa.pevfa.arguments import PEVFA_ARGUMENTS, action_space_errors_as_type_errors, pevfa_policy_kwargs
from sb3_pevfa.ppo_pevfa.policies import CnnPolicy, MlpPolicy, MultiInputPolicy, PeVFAActorCriticPolicy


class PPOPeVFA(PeVFAAlgorithm, PPO):
    """PPO whose critic is a PeVFA V(s, chi_pi), trained on the data of all historical policies.

    Paper: "What About Inputting Policy in Value Function: Policy Representation and Policy-extended Value
    Function Approximator" (Tang et al.). The actor update is SB3's PPO, unchanged. Per iteration
    (:meth:`~sb3_pevfa.pevfa.algorithm.PeVFAAlgorithm.train`):

    1. roll out pi_t; its record (parameters, state-action pairs) enters ``self.history`` before the rollout, and
       its ``(observation, value target)`` samples when it ends;
    2. extra critic updates on historical samples (policies 0..t-1), chi recomputed by the current encoder:
       one ``history_batch_size`` batch (of ``history_batch_policies`` policies) per ``history_train_freq``
       environment steps after ``history_learning_starts`` steps; the value loss also trains the encoder (E2E).
       The defaults (256 samples of 8 policies per 40 steps) feed the critic as many historical samples per step
       as the paper's schedule (``history_batch_size=64, history_batch_policies=None, history_train_freq=10``)
       in a quarter of the steps (docs/notes/2026-12-02-cheaper-history-schedule.md);
    3. ``update_order="joint"`` (default): SB3's joint actor-critic update, values use chi of pi_t's record;
       ``"critic_first"`` (the authors' order): critic epochs on the rollout, GAE recomputed with the updated
       critic, then the actor epochs with the critic frozen.

    Parameters not listed are SB3 PPO's (:class:`~stable_baselines3.PPO`).

    :param representation: Policy representation: ``opr`` (parameters), ``spr`` (state-action pairs),
        ``fingerprint`` (the actor's outputs at learned probe states), ``rpr`` (raw parameters), ``random``, ``stats``
        (parameter statistics) or ``none`` (conventional critic)
    :param embedding_dim: Size of chi (``opr``, ``spr``, ``fingerprint``, ``random``)
    :param representation_kwargs: Keyword arguments of the representation
    :param n_state_action_pairs: State-action pairs recorded per policy (SPR's data; 0 for image observations)
    :param representation_objectives: Extra encoder objectives besides the end-to-end value loss: any of
        ``"cl"`` (contrastive, InfoNCE with a momentum encoder) and ``"aux"`` (action prediction); ``opr``/``spr`` only
    :param objective_kwargs: Settings per objective, e.g. ``{"cl": {"batch_policies": 16, "momentum": 0.05}}``
        (see :mod:`sb3_pevfa.pevfa.objectives`)
    :param critic_learning_rate: Learning rate of the critic and encoder (float or schedule); None: ``learning_rate``
        (paper: actor 1e-4, critic 1e-3)
    :param update_order: ``joint`` (SB3) or ``critic_first`` (paper)
    :param value_target_lambda: Lambda of the value targets; None: ``gae_lambda`` (SB3's TD(lambda) returns),
        1.0: Monte-Carlo style returns as in the paper (bootstrapped at the end of the rollout only)
    :param history_buffer_size: Samples kept in the history FIFO (paper: 200k)
    :param history_max_policies: Policies kept in the history
    :param history_batch_size: Samples per historical critic update (paper: 64)
    :param history_batch_policies: Policies per historical batch: ``history_batch_size / history_batch_policies``
        samples of each, policies drawn in proportion to their sample counts (the same expected loss as uniform
        samples, at most this many policies to encode per batch); None: uniform samples (the paper's)
    :param history_train_freq: Environment steps per historical critic update (paper: 10); 0 disables them. Also
        the cadence of the CL objective unless its ``train_freq`` is given (the paper's 10 where this is 0)
    :param history_learning_starts: Environment steps before historical updates start (paper: 5k)
    :param history_targets: Value targets of the historical samples: ``"rollout"`` (the rollout's returns, computed
        once with the critic of that moment) or ``"recomputed"``: lambda-returns (lambda of the value targets)
        recomputed with the current critic at the chi of each sample's own policy
    :param history_target_refresh: Iterations between two recomputations of the historical targets
    :param history_normalization: Under SB3's ``VecNormalize``: ``"current"`` keeps raw observations and each
        target's reward scale and reads them in today's statistics (docs/history.md); ``"rollout"``: as the rollout
        saw them, stale once the statistics move (the behaviour before 0.1.0, an ablation). No effect without one
    :param rollout_encoder_gradient: The value loss on the rollout also trains the encoder (chi of the behaviour
        policy recomputed with gradient per minibatch, as the paper's E2E); False: that chi is computed once per
        update without gradient, and the encoder learns from the historical updates and the objectives; None
        (default): False where historical updates run (``history_train_freq > 0``), else True
    :param fast_path: Critic values batched after each rollout, the actor alone acting
        (:mod:`sb3_pevfa.pevfa.fast_path`): SB3's math and random draws, equal up to float round-off; False runs
        SB3's own ``collect_rollouts``. Both paths train with SB3's ``PPO.train``
    :param rollout_episodes: None: rollouts of ``n_steps`` (SB3's); k: rollouts of whole episodes of one env, ended at
        the first episode end after k episodes or ``n_steps`` steps (the authors' iterations,
        :mod:`sb3_pevfa.pevfa.episodes`); the historical updates then run per episode, as the authors count them
    :param bootstrap_truncated: SB3's bootstrap of an episode cut by a time limit with the value of its last
        observation; False: it ends as a terminal one (the authors', with a time feature in the observation)
    :param train_on_clipped_actions: The actor update's log-probabilities are of the actions the env received (clipped
        to the Box), as the authors' code stores them; False: of the sampled actions (SB3's)
    :param critic_minibatches: The critic's minibatches in the ``critic_first`` order: ``"sb3"`` (``batch_size`` each,
        the last one shorter) or ``"even"`` (N // (N // batch_size) samples each, the remainder left out: the authors')
    :param actor_batch_size: Minibatch size of the actor update in the ``critic_first`` order: None (``batch_size``),
        an int, or ``"full"`` (the whole rollout: ``n_epochs`` full-batch steps, the authors')
    :param flush_denormal: Denormal numbers flushed to zero during the update with one torch thread
        (``torch.set_flush_denormal``, the thread's setting restored after; :mod:`sb3_pevfa.pevfa.denormals`): Adam's
        moments of ReLU units without gradient decay through the denormal range, where the CPU is tens of times
        slower; False: IEEE denormals
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
        learning_rate: float | Schedule = 3e-4,
        n_steps: int = 2048,
        batch_size: int = 64,
        n_epochs: int = 10,
        gamma: float = 0.99,
        gae_lambda: float = 0.95,
        clip_range: float | Schedule = 0.2,
        clip_range_vf: float | Schedule | None = None,
        normalize_advantage: bool = True,
        ent_coef: float = 0.0,
        vf_coef: float = 0.5,
        max_grad_norm: float = 0.5,
        use_sde: bool = False,
        sde_sample_freq: int = -1,
        rollout_buffer_class: type[RolloutBuffer] | None = None,
        rollout_buffer_kwargs: dict[str, Any] | None = None,
        target_kl: float | None = None,
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
        history_train_freq: int = 40,
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
        actor_batch_size: int | str | None = None,
        policy_kwargs: dict[str, Any] | None = None,
        verbose: int = 0,
        seed: int | None = None,
        device: th.device | str = "auto",
        _init_setup_model: bool = True,
    ):
        pevfa = {name: value for name, value in locals().items() if name in PEVFA_ARGUMENTS}
        # no update takes minibatches of batch_size: SB3's warning of a truncated one would not be true
        own_batches = critic_minibatches == "even" and actor_batch_size is not None
        with action_space_errors_as_type_errors(), warnings.catch_warnings():
            if own_batches:
                warnings.filterwarnings("ignore", "You have specified a mini-batch size", UserWarning)
            super().__init__(
                policy,
                env,
                learning_rate=learning_rate,
                n_steps=n_steps,
                batch_size=batch_size,
                n_epochs=n_epochs,
                gamma=gamma,
                gae_lambda=gae_lambda,
                clip_range=clip_range,
                clip_range_vf=clip_range_vf,
                normalize_advantage=normalize_advantage,
                ent_coef=ent_coef,
                vf_coef=vf_coef,
                max_grad_norm=max_grad_norm,
                use_sde=use_sde,
                sde_sample_freq=sde_sample_freq,
                rollout_buffer_class=rollout_buffer_class,
                rollout_buffer_kwargs=rollout_buffer_kwargs,
                target_kl=target_kl,
                stats_window_size=stats_window_size,
                tensorboard_log=tensorboard_log,
                policy_kwargs=pevfa_policy_kwargs(policy_kwargs, pevfa),
                verbose=verbose,
                seed=seed,
                device=device,
                _init_setup_model=False,
            )
        self._init_pevfa(env, pevfa)
        self.actor_batch_size = actor_batch_size
        self._check_actor_batch_size()
        rollout_size = self.n_steps * self.n_envs if self.env is not None and rollout_episodes is None else None
        if own_batches and isinstance(actor_batch_size, int) and rollout_size and rollout_size % actor_batch_size:
            warnings.warn(
                f"actor_batch_size={actor_batch_size} leaves a truncated actor minibatch of "
                f"{rollout_size % actor_batch_size} samples of each rollout of n_steps * n_envs = {rollout_size}",
                stacklevel=2,
            )
        if _init_setup_model:
            self._setup_model()

    def _check_actor_batch_size(self) -> None:
        """``actor_batch_size`` as the model holds it (given to the constructor, or to ``load``)."""
        size = self.actor_batch_size
        valid_int = isinstance(size, int) and not isinstance(size, bool) and size > 1
        if not (size is None or size == "full" or valid_int):
            raise ValueError(f"actor_batch_size must be None, an int > 1 or 'full', got {size!r}")
        if size is not None and self.update_order != "critic_first":
            raise ValueError("actor_batch_size is the actor's own minibatch size of update_order='critic_first'")

    def _setup_model(self) -> None:
        self._check_actor_batch_size()  # again: load() sets its keyword arguments on the model before this
        super()._setup_model()

    def _rollout_critic_schedule(self) -> tuple[int, int]:
        return self.n_epochs, self.batch_size

    def _train_actor_critic(self) -> None:
        """SB3's ``PPO.train``, in minibatches of ``actor_batch_size`` where it is set."""
        if self.actor_batch_size is None:
            return super()._train_actor_critic()
        batch_size = self.batch_size
        rollout_size = self.rollout_buffer.buffer_size * self.rollout_buffer.n_envs
        self.batch_size = rollout_size if self.actor_batch_size == "full" else self.actor_batch_size
        try:
            super()._train_actor_critic()
        finally:
            self.batch_size = batch_size
