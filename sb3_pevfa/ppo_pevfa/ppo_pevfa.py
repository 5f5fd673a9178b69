"""PPO with a Policy-extended Value Function Approximator (PPO-PeVFA, paper Algorithm 2)."""

import io
import pathlib
from collections.abc import Generator
from typing import Any, ClassVar, TypeVar

import numpy as np
import torch as th
from gymnasium import spaces
from stable_baselines3 import PPO
from stable_baselines3.common.buffers import RolloutBuffer
from stable_baselines3.common.callbacks import BaseCallback, ConvertCallback
from stable_baselines3.common.env_util import make_vec_env
from stable_baselines3.common.policies import BasePolicy
from stable_baselines3.common.type_aliases import GymEnv, MaybeCallback, Schedule
from stable_baselines3.common.utils import FloatSchedule, obs_as_tensor
from stable_baselines3.common.vec_env import VecEnv
from torch.nn import functional as F

from sb3_pevfa.common import lean_ppo
from sb3_pevfa.common.buffers import PeVFADictRolloutBuffer, PeVFARolloutBuffer, _ValueTargetLambdaMixin
from sb3_pevfa.common.callbacks import PolicyHistoryCallback
from sb3_pevfa.common.history import PolicyHistory
from sb3_pevfa.common.policy_data import PolicyData
from sb3_pevfa.common.representations import REPRESENTATIONS
from sb3_pevfa.ppo_pevfa.policies import CnnPolicy, MlpPolicy, MultiInputPolicy, PeVFAActorCriticPolicy

SelfPPOPeVFA = TypeVar("SelfPPOPeVFA", bound="PPOPeVFA")

#: Valid values of ``update_order``.
UPDATE_ORDERS = ("joint", "critic_first")


_SUPPORTED_OBSERVATION_SPACES = (spaces.Box, spaces.Discrete, spaces.MultiDiscrete, spaces.MultiBinary)


def _check_observation_space(observation_space: spaces.Space) -> None:
    subspaces = observation_space.spaces.values() if isinstance(observation_space, spaces.Dict) else [observation_space]
    for space in subspaces:
        if not isinstance(space, _SUPPORTED_OBSERVATION_SPACES):
            raise TypeError(
                f"PPOPeVFA supports observation spaces {[s.__name__ for s in _SUPPORTED_OBSERVATION_SPACES]} "
                f"and Dict of them, got {observation_space}"
            )


class PPOPeVFA(PPO):
    """PPO whose critic is a PeVFA V(s, chi_pi), trained on the data of all historical policies.

    Paper: "What About Inputting Policy in Value Function: Policy Representation and Policy-extended Value
    Function Approximator" (Tang et al.). The actor update is SB3's PPO, unchanged. Per iteration:

    1. roll out pi_t; its raw data (parameters, state-action pairs) was recorded in ``self.history`` when the
       rollout started, and its ``(observation, value target)`` samples are appended when it ends;
    2. extra critic updates on historical samples (policies 0..t-1), chi recomputed by the current encoder:
       one ``history_batch_size`` batch per ``history_train_freq`` environment steps after
       ``history_learning_starts`` steps; the value loss also trains the encoder (E2E);
    3. ``update_order="joint"`` (default): SB3's joint actor-critic update, values use chi of pi_t's record;
       ``"critic_first"`` (the authors' order): critic epochs on the rollout, GAE recomputed with the updated
       critic, then the actor epochs with the critic frozen.

    Parameters not listed are SB3 PPO's (:class:`~stable_baselines3.PPO`).

    :param representation: Policy representation: ``opr`` (parameters), ``spr`` (state-action pairs),
        ``rpr`` (raw parameters), ``random``, ``stats`` (parameter statistics) or ``none`` (conventional critic)
    :param embedding_dim: Size of chi (``opr``, ``spr``, ``random``)
    :param representation_kwargs: Keyword arguments of the representation
    :param n_state_action_pairs: State-action pairs recorded per policy (SPR's data; 0 for image observations)
    :param representation_objectives: Extra encoder objectives besides the end-to-end value loss: any of
        ``"cl"`` (contrastive, InfoNCE with a momentum encoder) and ``"aux"`` (action prediction); ``opr``/``spr`` only
    :param objective_kwargs: Settings per objective, e.g. ``{"cl": {"batch_policies": 16, "momentum": 0.05}}``
        (see :mod:`sb3_pevfa.common.objectives`)
    :param critic_learning_rate: Learning rate of the critic and encoder (float or schedule); None: ``learning_rate``
        (paper: actor 1e-4, critic 1e-3)
    :param update_order: ``joint`` (SB3) or ``critic_first`` (paper)
    :param value_target_lambda: Lambda of the value targets; None: ``gae_lambda`` (SB3's TD(lambda) returns),
        1.0: Monte-Carlo style returns as in the paper (bootstrapped at the end of the rollout only)
    :param history_buffer_size: Samples kept in the history FIFO (paper: 200k)
    :param history_max_policies: Policies kept in the history
    :param history_batch_size: Samples per historical critic update (paper: 64)
    :param history_train_freq: Environment steps per historical critic update (paper: 10); 0 disables them
    :param history_learning_starts: Environment steps before historical updates start (paper: 5k)
    :param fast_path: Critic values batched after each rollout (the actor alone acts), a lean PPO update loop and
        foreach gradient clipping (:mod:`sb3_pevfa.common.lean_ppo`): SB3's math and random draws, equal up to float
        round-off; False runs SB3's own ``collect_rollouts`` and ``PPO.train``
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
        history_batch_size: int = 64,
        history_train_freq: int = 10,
        history_learning_starts: int = 5_000,
        fast_path: bool = True,
        policy_kwargs: dict[str, Any] | None = None,
        verbose: int = 0,
        seed: int | None = None,
        device: th.device | str = "auto",
        _init_setup_model: bool = True,
    ):
        pevfa_policy_kwargs = dict(
            representation=representation,
            embedding_dim=embedding_dim,
            representation_kwargs=representation_kwargs,
            n_state_action_pairs=n_state_action_pairs,
            representation_objectives=tuple(representation_objectives),
            objective_kwargs=objective_kwargs,
        )
        policy_kwargs = dict(policy_kwargs or {})
        clash = sorted(set(policy_kwargs) & set(pevfa_policy_kwargs))
        if clash:
            raise ValueError(f"Pass {clash} as PPOPeVFA arguments, not in policy_kwargs")
        policy_kwargs.update(pevfa_policy_kwargs)
        try:
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
                policy_kwargs=policy_kwargs,
                verbose=verbose,
                seed=seed,
                device=device,
                _init_setup_model=False,
            )
        except AssertionError as error:  # SB3 asserts on unsupported action spaces: make it a precise TypeError
            if "action spaces" in str(error):
                raise TypeError(str(error)) from error
            raise
        if self.env is not None:
            _check_observation_space(self.observation_space)
        # Kept so that a model loaded without an env (env=None) can still learn on: see learn()
        self.env_id = env if isinstance(env, str) else None
        self.representation = representation
        self.embedding_dim = embedding_dim
        self.critic_learning_rate = critic_learning_rate
        self.update_order = update_order
        self.value_target_lambda = value_target_lambda
        self.history_buffer_size = history_buffer_size
        self.history_max_policies = history_max_policies
        self.history_batch_size = history_batch_size
        self.history_train_freq = history_train_freq
        self.history_learning_starts = history_learning_starts
        self.fast_path = fast_path
        self._history_credit = 0
        self._objective_credit: dict[str, int] = {}
        self._validate_pevfa_arguments(n_state_action_pairs)
        if _init_setup_model:
            self._setup_model()

    def _validate_pevfa_arguments(self, n_state_action_pairs: int) -> None:
        if self.representation not in REPRESENTATIONS:
            raise ValueError(f"Unknown representation {self.representation!r}, valid choices: {REPRESENTATIONS}")
        if self.update_order not in UPDATE_ORDERS:
            raise ValueError(f"Unknown update_order {self.update_order!r}, valid choices: {UPDATE_ORDERS}")
        positive = {
            "embedding_dim": self.embedding_dim,
            "history_buffer_size": self.history_buffer_size,
            "history_max_policies": self.history_max_policies,
            "history_batch_size": self.history_batch_size,
        }
        non_negative = {
            "history_train_freq": self.history_train_freq,
            "history_learning_starts": self.history_learning_starts,
            "n_state_action_pairs": n_state_action_pairs,
        }
        for name, value in positive.items():
            if not isinstance(value, (int, np.integer)) or isinstance(value, bool) or value <= 0:
                raise ValueError(f"{name} must be a positive int, got {value!r}")
        for name, value in non_negative.items():
            if not isinstance(value, (int, np.integer)) or isinstance(value, bool) or value < 0:
                raise ValueError(f"{name} must be an int >= 0, got {value!r}")
        lr = self.critic_learning_rate
        if lr is not None and not callable(lr) and (not isinstance(lr, (int, float)) or lr <= 0):
            raise ValueError(f"critic_learning_rate must be a positive float, a schedule or None, got {lr!r}")
        lam = self.value_target_lambda
        if lam is not None and (not isinstance(lam, (int, float)) or not 0.0 <= lam <= 1.0):
            raise ValueError(f"value_target_lambda must be in [0, 1] or None, got {lam!r}")

    def _setup_model(self) -> None:
        if not (isinstance(self.policy_class, type) and issubclass(self.policy_class, PeVFAActorCriticPolicy)):
            raise TypeError(
                f"PPOPeVFA needs a PeVFA policy (one of {sorted(self.policy_aliases)} or a subclass of "
                f"PeVFAActorCriticPolicy), got {self.policy_class}"
            )
        if self.rollout_buffer_class is None:
            dict_obs = isinstance(self.observation_space, spaces.Dict)
            self.rollout_buffer_class = PeVFADictRolloutBuffer if dict_obs else PeVFARolloutBuffer
        if self.value_target_lambda is not None:
            if not issubclass(self.rollout_buffer_class, _ValueTargetLambdaMixin):
                raise ValueError(
                    "value_target_lambda needs PeVFARolloutBuffer or PeVFADictRolloutBuffer (or a subclass) "
                    f"as rollout_buffer_class, got {self.rollout_buffer_class.__name__}"
                )
            self.rollout_buffer_kwargs = {**self.rollout_buffer_kwargs, "value_target_lambda": self.value_target_lambda}
        super()._setup_model()
        self.critic_lr_schedule = (
            self.lr_schedule if self.critic_learning_rate is None else FloatSchedule(self.critic_learning_rate)
        )
        self.history = PolicyHistory(
            self.observation_space,
            self.action_space,
            self.policy.layout.n_params,
            n_state_action_pairs=self.policy.n_state_action_pairs,
            code_dim=self.policy.code_dim,
            buffer_size=self.history_buffer_size,
            max_policies=self.history_max_policies,
            seed=self.seed,
            representation=self.representation,
        )
        self._history_callback = PolicyHistoryCallback(self.history)
        self._critic_params = list(self.policy.critic_parameters())

    def _get_torch_save_params(self) -> tuple[list[str], list[str]]:
        state_dicts, variables = super()._get_torch_save_params()
        state_dicts += [f"policy.{name}_optimizer" for name in self.policy.objectives]
        return state_dicts, variables

    def _excluded_save_params(self) -> list[str]:
        return [*super()._excluded_save_params(), "history", "_history_callback", "_critic_params"]

    def _init_callback(self, callback: MaybeCallback, progress_bar: bool = False) -> BaseCallback:
        callbacks: list[BaseCallback] = [self._history_callback]
        if isinstance(callback, list):
            callbacks.extend(callback)
        elif callback is not None:
            callbacks.append(callback if isinstance(callback, BaseCallback) else ConvertCallback(callback))
        return super()._init_callback(callbacks, progress_bar)

    def _update_learning_rate(self, optimizers: list[th.optim.Optimizer] | th.optim.Optimizer) -> None:
        super()._update_learning_rate(optimizers)
        critic_lr = self.critic_lr_schedule(self._current_progress_remaining)
        self.logger.record("pevfa/critic_learning_rate", critic_lr)
        for group in self.policy.optimizer.param_groups:
            if group.get("name") == "critic":
                group["lr"] = critic_lr

    # ------------------------------------------------------------------ training
    def collect_rollouts(
        self, env: VecEnv, callback: BaseCallback, rollout_buffer: RolloutBuffer, n_rollout_steps: int
    ) -> bool:
        if self.fast_path:
            return lean_ppo.collect_rollouts(self, env, callback, rollout_buffer, n_rollout_steps)
        return super().collect_rollouts(env, callback, rollout_buffer, n_rollout_steps)

    def _ppo_update(self) -> None:
        """The PPO actor-critic update on the rollout (SB3's, or its lean equivalent)."""
        if self.fast_path:
            self.policy.set_training_mode(True)
            lean_ppo.train_ppo(self)
        else:
            super().train()

    def _critic_step(self, loss: th.Tensor) -> None:
        self.policy.optimizer.zero_grad()
        loss.backward()
        if self.fast_path:
            lean_ppo.clip_grad_norm(self._critic_params, self.max_grad_norm)
        else:
            th.nn.utils.clip_grad_norm_(self._critic_params, self.max_grad_norm)
        self.policy.optimizer.step()

    def _train_on_history(self) -> list[float]:
        """Extra critic updates on the samples of historical policies (Algorithm 2, line 8)."""
        if self.history_train_freq == 0 or self.num_timesteps < self.history_learning_starts:
            return []
        self._history_credit += self.n_steps * self.n_envs
        n_updates, self._history_credit = divmod(self._history_credit, self.history_train_freq)
        current = self.history.latest_policy_id
        losses = []
        for _ in range(n_updates):
            batch = self.history.sample(self.history_batch_size, exclude_policy=current)
            if batch is None:
                break
            observations, targets, policy_ids = batch
            unique_ids, inverse = np.unique(policy_ids, return_inverse=True)
            fields = self.policy.representation.fields
            data = PolicyData.from_numpy(self.history.policy_data(unique_ids, fields), self.device)
            embeddings = self.policy.embed(data)[th.as_tensor(inverse, device=self.device)]
            values = self.policy.predict_policy_values(obs_as_tensor(observations, self.device), embeddings)
            loss = F.mse_loss(values.flatten(), th.as_tensor(targets, device=self.device))
            self._critic_step(loss)
            losses.append(loss.item())
        return losses

    def _train_objectives(self) -> dict[str, list[float]]:
        """CL / AUX steps on batches of recorded policies (Algorithm 3), each on its own schedule and optimizer."""
        metrics: dict[str, list[float]] = {}
        for name, objective in self.policy.objectives.items():
            if self.num_timesteps < objective.learning_starts:
                continue
            credit = self._objective_credit.get(name, 0) + self.n_steps * self.n_envs
            n_updates, self._objective_credit[name] = divmod(credit, objective.train_freq)
            optimizer = getattr(self.policy, f"{name}_optimizer")
            metrics[f"{name}_updates"] = []
            for _ in range(n_updates):
                policy_ids = self.history.sample_policy_ids(objective.batch_policies)
                if len(policy_ids) < 2:  # a contrast needs negatives; AUX waits as well
                    break
                data = PolicyData.from_numpy(self.history.policy_data(policy_ids), self.device)
                loss, values = objective.loss(self.policy.representation, data)
                optimizer.zero_grad()
                loss.backward()
                optimizer.step()
                objective.after_step(self.policy.representation)
                for key, value in values.items():
                    metrics.setdefault(key, []).append(value)
                metrics[f"{name}_updates"].append(1.0)
        return metrics

    def _minibatches(self, n: int) -> Generator[np.ndarray, None, None]:
        indices = np.random.permutation(n)
        for start in range(0, n, self.batch_size):
            yield indices[start : start + self.batch_size]

    def _train_critic_on_rollout(self) -> list[float]:
        """Critic epochs on the current rollout with chi of its behaviour policy (``critic_first`` order)."""
        observations = lean_ppo.flat_observations(self.rollout_buffer, self.device, env_major=False)
        returns = th.as_tensor(self.rollout_buffer.returns.reshape(-1), device=self.device)
        losses = []
        for _ in range(self.n_epochs):
            for index in self._minibatches(len(returns)):
                batch = (
                    {k: v[index] for k, v in observations.items()} if isinstance(observations, dict) else observations[index]
                )
                loss = F.mse_loss(self.policy.predict_values(batch).flatten(), returns[index])
                self._critic_step(loss)
                losses.append(loss.item())
        return losses

    def _recompute_advantages(self) -> None:
        """GAE with the updated critic (``critic_first`` order)."""
        buffer = self.rollout_buffer
        self.policy.set_training_mode(False)
        values = lean_ppo.predict_values(self.policy, lean_ppo.flat_observations(buffer, self.device, env_major=False))
        with th.no_grad():
            last_values = self.policy.predict_values(obs_as_tensor(self._last_obs, self.device))  # type: ignore[arg-type]
        buffer.values = values.cpu().numpy().reshape(buffer.buffer_size, buffer.n_envs).astype(np.float32)
        buffer.compute_returns_and_advantage(last_values, self._last_episode_starts)  # type: ignore[arg-type]
        self.policy.set_training_mode(True)

    def train(self) -> None:
        self.policy.set_training_mode(True)
        self._update_learning_rate(self.policy.optimizer)
        objective_metrics = self._train_objectives()
        history_losses = self._train_on_history()
        for key, values in objective_metrics.items():
            self.logger.record(f"pevfa/{key}", len(values) if key.endswith("_updates") else float(np.mean(values)))
        if self.update_order == "critic_first":
            critic_losses = self._train_critic_on_rollout()
            self.logger.record("pevfa/critic_value_loss", float(np.mean(critic_losses)))
            self._recompute_advantages()
            with self.policy.critic_frozen():
                self._ppo_update()
        else:
            self._ppo_update()
        self._record_pevfa_logs(history_losses)

    def _record_pevfa_logs(self, history_losses: list[float]) -> None:
        self.logger.record("pevfa/history_updates", len(history_losses))
        if history_losses:
            self.logger.record("pevfa/history_value_loss", float(np.mean(history_losses)))
        self.logger.record("pevfa/n_policies", self.history.n_policies)
        self.logger.record("pevfa/history_samples", self.history.n_samples)
        self.logger.record("pevfa/history_memory_mb", self.history.nbytes / 2**20)
        self.logger.record("pevfa/policy_id", self.history.latest_policy_id)
        if self.policy.representation.embedding_dim > 0:
            self.policy.set_training_mode(False)
            self.logger.record("pevfa/embedding_norm", self.policy.behaviour_embedding().norm().item())

    def learn(
        self: SelfPPOPeVFA,
        total_timesteps: int,
        callback: MaybeCallback = None,
        log_interval: int = 1,
        tb_log_name: str = "PPOPeVFA",
        reset_num_timesteps: bool = True,
        progress_bar: bool = False,
    ) -> SelfPPOPeVFA:
        if self.env is None and self.env_id is not None:
            # Loaded with env=None from a model that was built from an env id: rebuild that env (seeded).
            self.set_env(make_vec_env(self.env_id, n_envs=self.n_envs, seed=self.seed))
        return super().learn(
            total_timesteps=total_timesteps,
            callback=callback,
            log_interval=log_interval,
            tb_log_name=tb_log_name,
            reset_num_timesteps=reset_num_timesteps,
            progress_bar=progress_bar,
        )

    # ------------------------------------------------------------------ persistence
    def save_history(self, path: str | pathlib.Path) -> None:
        """Save the policy history (``.npz``; large, so apart from the model, as SB3 does with replay buffers)."""
        self.history.save(path)

    def load_history(self, path: str | pathlib.Path) -> None:
        """Load a history saved by :meth:`save_history`; it must match this model (representation, spaces, actor)."""
        self.history.load(path)

    def save_replay_buffer(self, path: str | pathlib.Path) -> None:
        """Alias of :meth:`save_history`, the name rl-zoo3's ``--save-replay-buffer`` calls."""
        self.save_history(path)

    def load_replay_buffer(self, path: str | pathlib.Path, truncate_last_traj: bool = True) -> None:
        """Alias of :meth:`load_history`, the name rl-zoo3's ``-i`` (continue training) calls.

        :param truncate_last_traj: Ignored (a HER replay buffer option of SB3)
        """
        self.load_history(path)

    def save(self, path: str | pathlib.Path | io.BufferedIOBase, exclude=None, include=None) -> None:
        # The global RNG states travel with the model so that a resumed run continues as an uninterrupted one.
        self._rng_states = {"torch": th.get_rng_state(), "numpy": np.random.get_state()}
        try:
            super().save(path, exclude=exclude, include=include)
        finally:
            del self._rng_states

    @classmethod
    def load(cls, path: str | pathlib.Path | io.BufferedIOBase, *args: Any, **kwargs: Any):  # type: ignore[override]
        model = super().load(path, *args, **kwargs)
        rng_states = model.__dict__.pop("_rng_states", None)
        if rng_states is not None and model.seed is not None:
            th.set_rng_state(rng_states["torch"])
            np.random.set_state(rng_states["numpy"])
        return model
