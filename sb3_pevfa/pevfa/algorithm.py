"""What every PeVFA algorithm adds to its SB3 on-policy base (paper Algorithm 2), as a mixin.

``class PPOPeVFA(PeVFAAlgorithm, PPO)`` and ``class A2CPeVFA(PeVFAAlgorithm, A2C)``: the base algorithm keeps its
loop (``learn`` -> ``collect_rollouts`` -> ``train``) and its actor-critic update; this mixin records each policy
before it acts, trains the critic on the history and the encoder on its objectives, and keeps the history's files.
One iteration, as :meth:`PeVFAAlgorithm.train` reads:

1. roll out pi_t (:meth:`collect_rollouts`): pi_t is recorded first and becomes the critic's behaviour policy; its
   ``(observation, value target)`` samples are appended to the history when the rollout ends, and a representation
   that reads rollouts gets its observations (``observe_rollout`` of the policy);
2. AUX, then CL steps on batches of recorded policies (:meth:`_train_objectives`);
3. extra critic updates on the samples of historical policies 0..t-1, chi recomputed by the current encoder
   (:meth:`_train_on_history`);
4. the base algorithm's actor-critic update on the rollout (``update_order="joint"``), or critic steps on the
   rollout, advantages recomputed with the updated critic, then the actor update with the critic frozen
   (``"critic_first"``, the authors' order).
"""

import inspect
import io
import math
import pathlib
import warnings
from typing import Any, TypeVar

import numpy as np
import torch as th
from gymnasium import spaces
from stable_baselines3.common.buffers import RolloutBuffer
from stable_baselines3.common.callbacks import BaseCallback
from stable_baselines3.common.env_util import make_vec_env
from stable_baselines3.common.on_policy_algorithm import OnPolicyAlgorithm
from stable_baselines3.common.type_aliases import GymEnv, MaybeCallback
from stable_baselines3.common.utils import FloatSchedule, obs_as_tensor
from stable_baselines3.common.vec_env import VecEnv, VecNormalize
from torch.nn import functional as F

from sb3_pevfa.common.checks import check_policy_class
from sb3_pevfa.common.model_file import ModelFile
from sb3_pevfa.pevfa import episodes, fast_path
from sb3_pevfa.pevfa.arguments import (
    ADDED_POLICY_KWARGS,
    PEVFA_ARGUMENTS,
    check_observation_space,
    validate_arguments,
    with_saved_critic,
)
from sb3_pevfa.pevfa.buffers import PeVFADictRolloutBuffer, PeVFARolloutBuffer, ValueTargetLambdaMixin
from sb3_pevfa.pevfa.checkpoints import checkpoint_history, enable_history_checkpoints, path_of_the_moment, warn_if_newer
from sb3_pevfa.pevfa.critics import CRITIC_DEFAULTS
from sb3_pevfa.pevfa.denormals import flush_denormals
from sb3_pevfa.pevfa.history import PolicyHistory
from sb3_pevfa.pevfa.normalization import RolloutRecorder, find_vec_normalize
from sb3_pevfa.pevfa.objectives import PAPER_TRAIN_FREQ, RepresentationObjective, training_rank
from sb3_pevfa.pevfa.policies import PeVFAActorCriticPolicy
from sb3_pevfa.pevfa.recorder import PolicyRecorder
from sb3_pevfa.pevfa.records import PolicyRecord, batch_size, rows

SelfPeVFAAlgorithm = TypeVar("SelfPeVFAAlgorithm", bound="PeVFAAlgorithm")

#: A history that can grow beyond this many bytes is announced with a warning at construction
HISTORY_MEMORY_WARNING_BYTES = 4 * 2**30


class PeVFAAlgorithm(ModelFile, OnPolicyAlgorithm):
    """The PeVFA part of an on-policy algorithm; subclasses list it before their SB3 base (see the module)."""

    added_policy_kwargs = ADDED_POLICY_KWARGS
    default_policy_kwargs = CRITIC_DEFAULTS
    policy: PeVFAActorCriticPolicy
    history: PolicyHistory
    recorder: PolicyRecorder
    n_epochs: int
    batch_size: int

    def _init_pevfa(self, env: Any, arguments: dict[str, Any]) -> None:
        """Keep and validate the PeVFA arguments (after the base constructor, before ``_setup_model``)."""
        validate_arguments(arguments)
        if self.env is not None:
            check_observation_space(self.observation_space, type(self).__name__)
        # Kept so that a model loaded without an env (env=None) can still learn on: see learn()
        self.env_id = env if isinstance(env, str) else None
        for name in PEVFA_ARGUMENTS[6:]:
            setattr(self, name, arguments[name])
        self.representation = arguments["representation"]
        self.embedding_dim = arguments["embedding_dim"]
        self._history_credit = 0
        self._objective_credit: dict[str, int] = {}
        self._rollout_episode_returns: list[float] = []

    def _pevfa_arguments(self) -> dict[str, Any]:
        """The PeVFA arguments as the model holds them: the constructor's, or those ``load`` set on it (the policy's
        from ``policy_kwargs``; the constructor's defaults where a file saved by an earlier version lacks one)."""
        defaults = {
            name: parameter.default
            for name, parameter in inspect.signature(type(self).__init__).parameters.items()
            if name in PEVFA_ARGUMENTS
        }
        held = {name: self.policy_kwargs[name] for name in ADDED_POLICY_KWARGS if name in self.policy_kwargs}
        return {**defaults, **held, **{name: vars(self)[name] for name in PEVFA_ARGUMENTS if name in vars(self)}}

    def _setup_model(self) -> None:
        check_policy_class(self, PeVFAActorCriticPolicy)
        validate_arguments(self._pevfa_arguments())  # again: load() sets its keyword arguments on the model before this
        if self.rollout_buffer_class is None:
            dict_obs = isinstance(self.observation_space, spaces.Dict)
            self.rollout_buffer_class = PeVFADictRolloutBuffer if dict_obs else PeVFARolloutBuffer
        if self.value_target_lambda is not None:
            if not issubclass(self.rollout_buffer_class, ValueTargetLambdaMixin):
                raise ValueError(
                    "value_target_lambda needs PeVFARolloutBuffer or PeVFADictRolloutBuffer (or a subclass) "
                    f"as rollout_buffer_class, got {self.rollout_buffer_class.__name__}"
                )
            self.rollout_buffer_kwargs = {**self.rollout_buffer_kwargs, "value_target_lambda": self.value_target_lambda}
        # a fresh model spells its critic out (pevfa_policy_kwargs); a loaded one without it is of the earlier stream
        self.policy_kwargs = with_saved_critic(self.policy_kwargs)
        if self.rollout_episodes is not None and self.n_envs != 1:
            raise ValueError(f"rollout_episodes collects whole episodes of one env, got n_envs={self.n_envs}")
        if self.rollout_episodes is not None and self.history_targets == "recomputed":
            raise ValueError("history_targets='recomputed' needs rollouts of n_steps: it does not take rollout_episodes")
        if self.train_on_clipped_actions and not isinstance(self.action_space, spaces.Box):
            raise ValueError(f"train_on_clipped_actions needs a Box action space, got {self.action_space}")
        if self.train_on_clipped_actions and self.policy_kwargs.get("squash_output", False):
            raise ValueError("train_on_clipped_actions stores the env's actions: not with squash_output=True (gSDE)")
        rollout_size = self.n_steps * self.n_envs
        if self.history_train_freq > 0 and self.history_buffer_size <= rollout_size:
            raise ValueError(
                f"history_buffer_size={self.history_buffer_size} holds no more than one rollout (n_steps * n_envs = "
                f"{rollout_size}): every sample would be the current policy's and no historical update would run; "
                "make it larger, or set history_train_freq=0 to turn the historical updates off"
            )
        super()._setup_model()
        self.critic_lr_schedule = (
            self.lr_schedule if self.critic_learning_rate is None else FloatSchedule(self.critic_learning_rate)
        )
        self._make_history()
        if self.history.max_nbytes > HISTORY_MEMORY_WARNING_BYTES:
            warnings.warn(
                f"The policy history can grow to {self.history.max_nbytes / 2**30:.1f} GiB (history_buffer_size="
                f"{self.history_buffer_size} samples, history_max_policies={self.history_max_policies} records); lower "
                "them, or n_state_action_pairs, to bound it",
                stacklevel=3,  # the user's constructor call
            )
        self.policy.behaviour_chi_gradient = self.trains_encoder_on_rollout
        self._critic_params = list(self.policy.critic_parameters())
        critic_ids = {id(p) for p in self._critic_params}
        # what a critic-only step must leave alone: a features extractor shared with the actor (CnnPolicy)
        self._shared_params = [p for p in self.policy.optimizer.param_groups[0]["params"] if id(p) not in critic_ids]

    def _make_history(self) -> None:
        """A new, empty history (and its recorder); under SB3's ``VecNormalize`` it keeps raw observations and hands
        them out in today's statistics (:mod:`~sb3_pevfa.pevfa.normalization`)."""
        vec_normalize = self._history_normalizer(self.env)
        renormalize = vec_normalize is not None
        self.history = PolicyHistory(
            self.observation_space,
            self.action_space,
            self.policy.layout.n_params,
            n_state_action_pairs=self.policy.n_recorded_pairs,
            code_dim=self.policy.code_dim,
            buffer_size=self.history_buffer_size,
            max_policies=self.history_max_policies,
            seed=self.seed,
            representation=self.representation,
            layout=self.policy.layout,
            transitions=self.history_targets == "recomputed",
            renormalize=renormalize,
        )
        self.history.normalizer = vec_normalize
        self.recorder = PolicyRecorder(self.history, self.policy.layout)
        self._raw_rollout: RolloutRecorder | None = None
        self._last_raw_obs: np.ndarray | dict | None = None  # raw of _last_obs (renormalize)

    def _history_normalizer(self, env: VecEnv | None) -> VecNormalize | None:
        """The ``VecNormalize`` whose statistics the history reads its samples in; None where it keeps them as the
        rollout saw them (no re-expressible ``VecNormalize``, or ``history_normalization="rollout"``)."""
        if self.history_normalization == "rollout":
            return None
        return find_vec_normalize(env, self.observation_space)

    def set_env(self, env: GymEnv, force_reset: bool = True) -> None:
        """SB3's ``set_env``; the history follows the new env's ``VecNormalize`` (a ``VecNormalize.load`` of the same
        run: its statistics). A history of raw observations cannot go to an env without one, nor the other way."""
        wrapped = self._wrap_env(env, self.verbose) if isinstance(env, VecEnv) else None  # as SB3 will wrap it
        vec_normalize = self._history_normalizer(wrapped)
        renormalize = vec_normalize is not None
        if renormalize != self.history.renormalize and self.history.n_policies:  # checked before anything changes
            raise ValueError(
                f"The policy history was recorded {'with' if self.history.renormalize else 'without'} a VecNormalize "
                f"env and the new env {'has one' if renormalize else 'has none'}: its observations cannot be "
                "re-expressed; wrap the env as it was (VecNormalize.load of the run's statistics)"
            )
        super().set_env(env, force_reset=force_reset)
        if renormalize != self.history.renormalize:
            self._make_history()
        self.history.normalizer = vec_normalize

    def _get_torch_save_params(self) -> tuple[list[str], list[str]]:
        state_dicts, variables = super()._get_torch_save_params()
        state_dicts += [f"policy.{name}_optimizer" for name in self.policy.objectives]
        return state_dicts, variables

    def _excluded_save_params(self) -> list[str]:
        return [
            *super()._excluded_save_params(),
            "history",
            "recorder",
            "_critic_params",
            "_shared_params",
            "_raw_rollout",
            "_last_raw_obs",
        ]

    @property
    def trains_encoder_on_rollout(self) -> bool:
        """Whether the on-policy value loss trains the encoder: ``rollout_encoder_gradient``, or where it is None,
        only without historical updates (they would otherwise be the encoder's only value-loss gradient)."""
        if self.rollout_encoder_gradient is None:
            return self.history_train_freq == 0
        return bool(self.rollout_encoder_gradient)

    def _update_learning_rate(self, optimizers: list[th.optim.Optimizer] | th.optim.Optimizer) -> None:
        super()._update_learning_rate(optimizers)
        critic_lr = self.critic_lr_schedule(self._current_progress_remaining)
        self.logger.record("pevfa/critic_learning_rate", critic_lr)
        for group in self.policy.optimizer.param_groups:
            if group.get("name") == "critic":
                group["lr"] = critic_lr
            elif "lr_scale" in group:  # e.g. the log-std's (log_std_lr_scale): the actor's rate, scaled
                group["lr"] = group["lr"] * group["lr_scale"]

    # ------------------------------------------------------------------ rollout: record, act, keep the samples
    def record_behaviour_policy(self) -> int:
        """Record the live policy (unless unchanged since the latest record) and make it the critic's behaviour
        policy: the one whose chi the rollout's values use. Returns its id."""
        assert self._last_obs is not None, "No previous observation was provided"
        self.policy.set_training_mode(False)  # as SB3's rollouts: batch norm and dropout in evaluation mode
        observations = self._last_raw_obs if self.history.renormalize else self._last_obs
        policy_id = self.recorder.record(
            self.policy, observations, n_updates=self._n_updates, num_timesteps=self.num_timesteps
        )
        record = PolicyRecord.from_numpy(self.history.records([policy_id]), self.device)
        self.policy.set_behaviour_record(record)
        return policy_id

    def collect_rollouts(
        self, env: VecEnv, callback: BaseCallback, rollout_buffer: RolloutBuffer, n_rollout_steps: int
    ) -> bool:
        policy_id = self.record_behaviour_policy()
        self._rollout_episode_returns = []
        if self.history.renormalize:
            self._raw_rollout = RolloutRecorder(self.history.normalizer, self._last_raw_obs)
        if self.fast_path:
            complete = fast_path.collect_rollouts(self, env, callback, rollout_buffer, n_rollout_steps)
        else:
            complete = super().collect_rollouts(env, callback, rollout_buffer, n_rollout_steps)
        if complete:
            self.policy.observe_rollout(rollout_buffer)  # for a representation that reads rollouts (rollout_rows)
            self.recorder.add_rollout(
                rollout_buffer,
                policy_id,
                self._rollout_episode_returns,
                self._last_obs,
                self._last_episode_starts,
                raw=self._raw_rollout,
            )
        self._raw_rollout = None
        return complete

    def _setup_learn(self, total_timesteps: int, *args: Any, **kwargs: Any) -> tuple[int, BaseCallback]:
        reads_history = self.history_train_freq > 0 or len(self.policy.objectives) > 0
        if self.num_timesteps > 0 and not self.history.n_policies and reads_history:  # after one learn() it is not empty
            warnings.warn(
                f"This model has trained {self.num_timesteps} steps but its policy history is empty (a model file "
                "holds no history): its historical critic updates start again from nothing. Call "
                "model.load_history(path) with the history saved beside it (save_history) to go on from it",
                stacklevel=5,  # the user's learn() (through PeVFAAlgorithm, PPO and OnPolicyAlgorithm.learn)
            )
        last_obs = self._last_obs
        result = super()._setup_learn(total_timesteps, *args, **kwargs)
        if self.history.renormalize and (self._last_obs is not last_obs or self._last_raw_obs is None):
            self._last_raw_obs = self.history.normalizer.get_original_obs()  # the env was reset: its raw observation
        return result

    def _update_info_buffer(self, infos: list[dict[str, Any]], dones: np.ndarray | None = None) -> None:
        super()._update_info_buffer(infos, dones)
        if self._raw_rollout is not None:
            self._raw_rollout.step()
            self._last_raw_obs = self._raw_rollout.observations[-1]
        self._rollout_episode_returns.extend(info["episode"]["r"] for info in infos if "episode" in info)

    # ------------------------------------------------------------------ training
    def _critic_step(self, loss: th.Tensor, what: str) -> float:
        """One step of the critic (and encoder) alone: the actor, a shared features extractor included, stays.
        Returns the loss; a non-finite one is an error before it reaches any parameter."""
        value = loss.item()
        if not math.isfinite(value):
            raise ValueError(f"The {what} is {value} (non-finite): the critic or its inputs hold NaN/inf; no step taken")
        self.policy.optimizer.zero_grad()
        loss.backward()
        for param in self._shared_params:
            param.grad = None  # Adam skips it: the actor's outputs, and so the rollout's log-probabilities, stay valid
        th.nn.utils.clip_grad_norm_(self._critic_params, self.max_grad_norm, foreach=True)
        self.policy.optimizer.step()
        self.policy.clear_embedding_cache()  # the encoder may have moved
        return value

    def _refresh_history_targets(self) -> int:
        """``history_targets="recomputed"``: every ``history_target_refresh`` iterations, each historical sample's
        target becomes the lambda-return of its own policy under the current critic, V(s, chi_k) at that policy's
        chi (the latest policy's samples keep the rollout's returns: the on-policy update trains on those).
        Returns the number of samples recomputed."""
        iteration = self.num_timesteps // (self.n_steps * self.n_envs)
        reads = self.history_train_freq > 0 and self.num_timesteps >= self.history_learning_starts
        if self.history_targets != "recomputed" or not reads or iteration % self.history_target_refresh:
            return 0
        lam = self.gae_lambda if self.value_target_lambda is None else self.value_target_lambda
        self.policy.set_training_mode(False)
        fields = self.policy.representation.fields

        def values(observations, policy_ids: np.ndarray) -> np.ndarray:
            unique_ids, inverse = np.unique(policy_ids, return_inverse=True)
            with th.no_grad():
                chi = self.policy.embed(PolicyRecord.from_numpy(self.history.records(unique_ids, fields), self.device))
            chi = chi[th.as_tensor(inverse, device=self.device)]
            return fast_path.predict_values(self.policy, obs_as_tensor(observations, self.device), chi).cpu().numpy()

        n = self.history.recompute_targets(values, self.gamma, lam, exclude_policy=self.history.latest_policy_id)
        self.policy.set_training_mode(True)
        return n

    def _train_on_history(self) -> list[float]:
        """Extra critic updates on the samples of historical policies (Algorithm 2, line 8)."""
        if self.history_train_freq == 0:
            return []
        if self.rollout_episodes is not None:  # the authors' count, at each episode's end
            lengths = episodes.episode_lengths(self.rollout_buffer.episode_starts)
            n_updates = int(
                episodes.historical_updates(
                    lengths, self.num_timesteps, self.history_train_freq, self.history_learning_starts
                ).sum()
            )
        elif self.num_timesteps < self.history_learning_starts:
            return []
        else:
            self._history_credit += self.n_steps * self.n_envs
            n_updates, self._history_credit = divmod(self._history_credit, self.history_train_freq)
        current = self.history.latest_policy_id
        fields = self.policy.representation.fields
        losses = []
        for _ in range(n_updates):
            if self.history_batch_policies is None:
                batch = self.history.sample(self.history_batch_size, exclude_policy=current)
            else:
                batch = self.history.sample_grouped(self.history_batch_size, self.history_batch_policies, current)
            if batch is None:
                break
            observations, targets, policy_ids = batch
            unique_ids, inverse = np.unique(policy_ids, return_inverse=True)
            records = PolicyRecord.from_numpy(self.history.records(unique_ids, fields), self.device)
            chi = self.policy.embed(records)[th.as_tensor(inverse, device=self.device)]
            values = self.policy.predict_values(obs_as_tensor(observations, self.device), chi)
            loss = F.mse_loss(values.flatten(), th.as_tensor(targets, device=self.device))
            losses.append(self._critic_step(loss, "historical value loss"))
        return losses

    def _train_objectives(self) -> dict[str, list[float]]:
        """AUX, then CL steps on batches of recorded policies (Algorithm 3), each on its own schedule and optimizer."""
        metrics: dict[str, list[float]] = {}
        for name in sorted(self.policy.objectives, key=training_rank):
            objective = self.policy.objectives[name]
            if self.num_timesteps < objective.learning_starts:
                continue
            credit = self._objective_credit.get(name, 0) + self._rollout_size()
            n_updates, self._objective_credit[name] = divmod(credit, self.objective_train_freq(objective))
            optimizer = getattr(self.policy, f"{name}_optimizer")
            metrics[f"{name}_updates"] = []
            for _ in range(n_updates):
                policy_ids = self.history.sample_policy_ids(objective.batch_policies)
                if len(policy_ids) < 2:  # a contrast needs negatives; AUX waits as well
                    break
                records = PolicyRecord.from_numpy(self.history.records(policy_ids), self.device)
                loss, values = objective.loss(self.policy.representation, records)
                if not th.isfinite(loss):
                    raise ValueError(f"The {name} objective's loss is {loss.item()} (non-finite); no step taken")
                optimizer.zero_grad()
                loss.backward()
                optimizer.step()
                objective.after_step(self.policy.representation)
                self.policy.clear_embedding_cache()  # the encoder has moved
                for key, value in values.items():
                    metrics.setdefault(key, []).append(value)
                metrics[f"{name}_updates"].append(1.0)
            optimizer.zero_grad()  # no stale gradient of the objective's own modules in the next update's clip norm
        return metrics

    def _rollout_size(self) -> int:
        """Env steps of the latest rollout: ``n_steps * n_envs``, or what a rollout of whole episodes collected."""
        return self.rollout_buffer.buffer_size * self.n_envs

    def objective_train_freq(self, objective: RepresentationObjective) -> int:
        """Environment steps per step of ``objective``: its own ``train_freq``, else ``history_train_freq`` (the
        historical critic updates' cadence), else the paper's 10."""
        return objective.train_freq or self.history_train_freq or PAPER_TRAIN_FREQ

    def _rollout_critic_schedule(self) -> tuple[int, int]:
        """Epochs and minibatch size of the critic's steps on the rollout in the ``critic_first`` order."""
        raise NotImplementedError

    def rollout_critic_minibatches(self, n: int) -> tuple[int, int, int]:
        """Epochs, minibatch size and the samples used (of ``n`` shuffled ones) of the critic's fit to a rollout of
        ``n`` samples in the ``critic_first`` order (also what a conventional critic beside the run trains on): the
        remainder is the last minibatch, or with ``critic_minibatches="even"`` the authors' split, N // (N //
        batch_size) samples each, the remainder left out."""
        n_epochs, batch_size = self._rollout_critic_schedule()
        if self.critic_minibatches != "even":
            return n_epochs, batch_size, n
        n_batches = max(n // batch_size, 1)
        return n_epochs, n // n_batches, n_batches * (n // n_batches)

    def _train_critic_on_rollout(self) -> list[float]:
        """Critic epochs on the current rollout with chi of its behaviour policy (``critic_first`` order)."""
        observations = fast_path.flat_observations(self.rollout_buffer, self.device, env_major=False)
        returns = th.as_tensor(self.rollout_buffer.returns.reshape(-1), device=self.device)
        n_epochs, batch_size, stop = self.rollout_critic_minibatches(len(returns))
        n = len(returns)
        losses = []
        for _ in range(n_epochs):
            indices = np.random.permutation(n)
            for start in range(0, stop, batch_size):
                index = indices[start : start + batch_size]
                batch = rows(observations, index)
                loss = F.mse_loss(self.policy.predict_values(batch).flatten(), returns[index])
                losses.append(self._critic_step(loss, "value loss of the critic-first epochs"))
        return losses

    def _recompute_advantages(self) -> None:
        """GAE with the updated critic (``critic_first`` order)."""
        buffer = self.rollout_buffer
        self.policy.set_training_mode(False)
        values = fast_path.predict_values(self.policy, fast_path.flat_observations(buffer, self.device, env_major=False))
        with th.no_grad():
            last_values = self.policy.predict_values(obs_as_tensor(self._last_obs, self.device))  # type: ignore[arg-type]
        buffer.values = values.cpu().numpy().reshape(buffer.buffer_size, buffer.n_envs).astype(np.float32)
        buffer.compute_returns_and_advantage(last_values, self._last_episode_starts)  # type: ignore[arg-type]
        self.policy.set_training_mode(True)

    def _train_actor_critic(self) -> None:
        """The base algorithm's actor-critic update on the rollout (SB3's ``train``)."""
        super().train()  # type: ignore[safe-super]

    def train(self) -> None:
        """One update (see the module), float32 denormals flushed to zero unless ``flush_denormal`` is False
        (:mod:`~sb3_pevfa.pevfa.denormals`)."""
        with flush_denormals(self.flush_denormal):
            self._train_pevfa()

    def _train_pevfa(self) -> None:
        self.policy.behaviour_chi_gradient = self.trains_encoder_on_rollout  # an attribute changed since is honoured
        self.policy.set_training_mode(True)
        self._update_learning_rate(self.policy.optimizer)
        objective_metrics = self._train_objectives()
        recomputed = self._refresh_history_targets()
        history_losses = self._train_on_history()
        for key, values in objective_metrics.items():
            self.logger.record(f"pevfa/{key}", len(values) if key.endswith("_updates") else float(np.mean(values)))
        if self.update_order == "critic_first":
            critic_losses = self._train_critic_on_rollout()
            self.logger.record("pevfa/critic_value_loss", float(np.mean(critic_losses)))
            self._recompute_advantages()
            with self.policy.critic_frozen():
                self._train_actor_critic()
        else:
            self._train_actor_critic()
        self.policy.clear_embedding_cache()  # the update may have moved the encoder
        self._record_pevfa_logs(history_losses)
        if self.history_targets == "recomputed":
            self.logger.record("pevfa/history_targets_recomputed", recomputed)

    def _record_pevfa_logs(self, history_losses: list[float]) -> None:
        self.logger.record("pevfa/history_updates", len(history_losses))
        if history_losses:
            self.logger.record("pevfa/history_value_loss", float(np.mean(history_losses)))
        self.logger.record("pevfa/n_policies", self.history.n_policies)
        self.logger.record("pevfa/history_samples", self.history.n_samples)
        self.logger.record("pevfa/history_memory_mb", self.history.nbytes / 2**20)
        self.logger.record("pevfa/policy_id", self.history.latest_policy_id)

    def dump_logs(self, iteration: int = 0) -> None:
        """SB3's, the embedding's diagnostics of the behaviour policy recorded first: computed only for the rows the
        logger writes (every ``log_interval`` iterations), not at every update."""
        if self.policy.representation.embedding_dim > 0 and self.rollout_buffer.full:
            self.policy.set_training_mode(False)
            chi = self.policy.behaviour_embedding()
            self.logger.record("pevfa/embedding_norm", chi.norm().item())
            self.logger.record("pevfa/embedding_saturated_fraction", self.policy.value_net.saturated_fraction(chi))
            self.logger.record("pevfa/value_chi_gradient", self.value_chi_gradient())
        super().dump_logs(iteration)

    def value_chi_gradient(self, n_states: int = 256) -> float:
        """Mean over (up to ``n_states``) states of the rollout of ``||dV(s, chi)/dchi||`` at the behaviour policy's
        chi: how much the critic's value reacts to the policy embedding (0: it cannot tell policies apart)."""
        observations = fast_path.flat_observations(self.rollout_buffer, self.device, env_major=False)
        observations = rows(observations, slice(0, n_states))
        with th.no_grad():
            chi = self.policy.behaviour_embedding()
        chi = chi.expand(batch_size(observations), -1).clone().requires_grad_(True)
        values = self.policy.predict_values(observations, chi)
        (gradient,) = th.autograd.grad(values.sum(), chi)
        return gradient.norm(dim=1).mean().item()

    def learn(
        self: SelfPeVFAAlgorithm,
        total_timesteps: int,
        callback: MaybeCallback = None,
        log_interval: int | None = None,
        tb_log_name: str | None = None,
        reset_num_timesteps: bool = True,
        progress_bar: bool = False,
    ) -> SelfPeVFAAlgorithm:
        if self.env is None and self.env_id is not None:
            # Loaded with env=None from a model that was built from an env id: rebuild that env (seeded).
            self.set_env(make_vec_env(self.env_id, n_envs=self.n_envs, seed=self.seed))
        self._require_env()
        kwargs = {} if log_interval is None else {"log_interval": log_interval}  # None: the base's (PPO 1, A2C 100)
        enable_history_checkpoints(callback)
        super().learn(
            total_timesteps=total_timesteps,
            callback=callback,
            tb_log_name=tb_log_name or type(self).__name__,
            reset_num_timesteps=reset_num_timesteps,
            progress_bar=progress_bar,
            **kwargs,
        )
        if self._last_obs is not None:
            self.record_behaviour_policy()  # the trained policy: the last record, and the critic's default
        return self

    # ------------------------------------------------------------------ persistence
    def save_history(self, path: str | pathlib.Path | io.IOBase) -> None:
        """Save the policy history (``.npz``; large, so apart from the model, as SB3 does with replay buffers)."""
        self.history.save(path)

    def load_history(self, path: str | pathlib.Path | io.IOBase) -> None:
        """Load a history saved by :meth:`save_history`; it must match this model (representation, spaces, actor).
        A history with records from after this model's ``num_timesteps`` (e.g. a run's final history beside one of
        its checkpoints) is loaded with a warning."""
        self.history.load(path)
        warn_if_newer(self.history, self.num_timesteps, path)

    @property
    def replay_buffer(self) -> PolicyHistory:
        """The history, under the name SB3's ``CheckpointCallback(save_replay_buffer=True)`` saves with each
        checkpoint (through :meth:`save_replay_buffer`)."""
        return self.history

    def save_replay_buffer(self, path: str | pathlib.Path | io.IOBase) -> None:
        """Alias of :meth:`save_history`, the name rl-zoo3's ``--save-replay-buffer`` calls."""
        self.save_history(path)

    def load_replay_buffer(self, path: str | pathlib.Path | io.IOBase, truncate_last_traj: bool = True) -> None:
        """Alias of :meth:`load_history`, the name rl-zoo3's ``-i`` (continue training) calls. rl-zoo3 passes the
        run's final ``replay_buffer.pkl`` also for a checkpoint: a history saved beside it at this model's
        ``num_timesteps`` (the checkpoint's own) is loaded instead.

        :param truncate_last_traj: Ignored (a HER replay buffer option of SB3)
        """
        self.load_history(path_of_the_moment(path, self.num_timesteps))

    @classmethod
    def load(  # type: ignore[override]
        cls, path: str | pathlib.Path | io.BufferedIOBase, *args: Any, restore_rng_state: bool = False, **kwargs: Any
    ):
        """SB3's ``load`` (the RNG states and a ``policy_kwargs`` given as :meth:`ModelFile.load` says). A checkpoint
        of SB3's ``CheckpointCallback`` (``<prefix>_<steps>_steps.zip``) comes with the history saved beside it, if
        there is one.

        :param restore_rng_state: Set the global torch / numpy RNG states to the saving process's, so that learning
            on (with :meth:`load_history` and seeded environments) continues bit for bit as the saved run would have
        """
        model = super().load(path, *args, restore_rng_state=restore_rng_state, **kwargs)
        history = checkpoint_history(path) if isinstance(path, (str, pathlib.Path)) else None
        if history is not None:  # a checkpoint of CheckpointCallback: its history was saved beside it
            try:
                model.load_history(history)
            except ValueError as error:  # e.g. loaded without its VecNormalize env (rl-zoo3's enjoy): the model is fine
                warnings.warn(f"The checkpoint's history {history} was not loaded: {error}", stacklevel=2)
        return model
