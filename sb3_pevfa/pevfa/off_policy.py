"""What a PeVFA adds to SB3's off-policy algorithms (SAC, TD3), as a mixin: a bounded history of actor snapshots and
extra critic updates for them.

``class SACPeVFA(OffPolicyPeVFA, SAC)``: SB3's ``train`` runs as it is, its critics reading chi of the live actor
(:class:`~sb3_pevfa.pevfa.q_critics.PeVFAContinuousCritic`), in pieces that end where the live actor is recorded
(every ``snapshot_freq`` gradient steps); after it, every ``history_train_freq`` gradient steps one critic update fits
Q(s, a, chi_k) of ``history_batch_policies`` snapshots k to their own targets on replay transitions:
r + gamma (1 - d) (min Q'(s', a'_k, chi'_k) [- alpha log pi_k(a'_k | s')]), a'_k drawn from snapshot k's actor
(:meth:`OffPolicyPeVFA._snapshot_actions`).
"""

import io
import pathlib
import warnings
from typing import Any

import numpy as np
import torch as th
from stable_baselines3.common.off_policy_algorithm import OffPolicyAlgorithm
from stable_baselines3.common.preprocessing import get_action_dim, get_obs_shape
from stable_baselines3.common.utils import obs_as_tensor, polyak_update
from stable_baselines3.her.her_replay_buffer import HerReplayBuffer
from torch.nn import functional as F

from sb3_pevfa.common.checks import check_argument_names, check_policy_class, init_parameters, is_int
from sb3_pevfa.common.files import replacing, with_default_suffix
from sb3_pevfa.common.model_file import ModelFile, sb3_algorithm
from sb3_pevfa.pevfa.checkpoints import path_of_the_moment, warn_if_newer
from sb3_pevfa.pevfa.denormals import flush_denormals
from sb3_pevfa.pevfa.history import PolicyHistory
from sb3_pevfa.pevfa.q_critics import OFF_POLICY_REPRESENTATIONS
from sb3_pevfa.pevfa.records import PolicyRecord, rows, state_dim

#: The snapshot arguments of an off-policy PeVFA algorithm's constructor
SNAPSHOT_ARGUMENTS = (
    "snapshot_freq",
    "history_max_policies",
    "history_train_freq",
    "history_batch_size",
    "history_batch_policies",
    "history_learning_starts",
)


#: The PeVFA arguments that build the policy (they travel in ``policy_kwargs``)
POLICY_ARGUMENTS = ("representation", "embedding_dim", "representation_kwargs", "n_state_action_pairs")


def off_policy_kwargs(policy_kwargs: dict[str, Any] | None, arguments: dict[str, Any]) -> dict[str, Any]:
    """``policy_kwargs`` with the policy's PeVFA arguments added (they may not be given twice)."""
    ours = {name: arguments[name] for name in POLICY_ARGUMENTS}
    clash = sorted(set(policy_kwargs or {}) & set(ours))
    if clash:
        raise ValueError(f"Pass {clash} as arguments of the algorithm, not in policy_kwargs")
    return {**(policy_kwargs or {}), **ours}


def check_snapshot_arguments(arguments: dict[str, Any]) -> None:
    """A ValueError naming the argument where one is not a valid int."""
    for name in SNAPSHOT_ARGUMENTS:
        value, least = arguments[name], 0 if name in ("history_train_freq", "history_learning_starts") else 1
        if not is_int(value) or value < least:
            raise ValueError(f"{name} must be an int >= {least}, got {value!r}")
    if arguments["history_batch_size"] % arguments["history_batch_policies"]:
        raise ValueError(
            f"history_batch_size ({arguments['history_batch_size']}) must be a multiple of history_batch_policies "
            f"({arguments['history_batch_policies']}): each snapshot gets as many transitions"
        )


def shuffled(data: Any) -> Any:
    """Replay samples (SB3's named tuple of tensors, or dicts of them) in a random order of their rows."""
    order = th.randperm(len(data.actions), device=data.actions.device)
    return type(data)(*(rows(field, order) if field is not None else None for field in data))


def snapshots_path(replay_buffer_path: str | pathlib.Path) -> pathlib.Path:
    """Where the snapshots saved with a replay buffer go: ``replay_buffer.pkl`` -> ``replay_buffer.snapshots.npz``."""
    path = pathlib.Path(replay_buffer_path)
    path = path if path.suffix == ".pkl" else path.with_name(path.name + ".pkl")  # SB3 adds .pkl where it is missing
    return path.with_suffix(".snapshots.npz")


class OffPolicyPeVFA(ModelFile, OffPolicyAlgorithm):
    """The snapshot history and its critic updates; subclasses list it before their SB3 base and implement
    :meth:`_snapshot_actions` (and :meth:`_entropy_term` where the target has one)."""

    added_policy_kwargs = POLICY_ARGUMENTS
    history: PolicyHistory
    #: The critic loss of SB3's update is this times the sum of the critics' MSE (SAC: 0.5, TD3: 1)
    critic_loss_scale: float = 1.0
    #: The names of SB3's lists of the critic's and its target's BatchNorm statistics
    critic_norm_stats: tuple[str, str] = ("critic_batch_norm_stats", "critic_batch_norm_stats_target")
    live_encoder_gradient: bool
    #: Denormals flushed to zero in ``train`` (models saved without the attribute load with it)
    flush_denormal: bool = True
    #: The snapshots' critic updates so far (logged as ``pevfa/n_history_updates``)
    _n_history_updates: int = 0
    snapshot_freq: int
    history_max_policies: int
    history_train_freq: int
    history_batch_size: int
    history_batch_policies: int
    history_learning_starts: int

    def __init__(
        self,
        policy: Any,
        env: Any,
        representation: str = "opr",
        embedding_dim: int = 64,
        representation_kwargs: dict[str, Any] | None = None,
        n_state_action_pairs: int = 200,
        snapshot_freq: int = 1000,
        history_max_policies: int = 100,
        history_train_freq: int = 4,
        history_batch_size: int = 512,
        history_batch_policies: int = 8,
        history_learning_starts: int = 0,
        live_encoder_gradient: bool = True,
        flush_denormal: bool = True,
        policy_kwargs: dict[str, Any] | None = None,
        _init_setup_model: bool = True,
        **kwargs: Any,
    ):
        """The PeVFA arguments (see the algorithm's docstring); the rest are the SB3 base's, by keyword."""
        if not isinstance(representation, str):  # SB3's third positional argument is its learning rate
            base = sb3_algorithm(type(self))
            raise TypeError(
                f"representation must be one of {OFF_POLICY_REPRESENTATIONS}, got {representation!r}: after the env come "
                f"the PeVFA arguments; pass {base}'s own (learning_rate, ...) by keyword"
            )
        check_argument_names(kwargs, init_parameters(type(self)), f"{type(self).__name__}()")  # not SB3's base's name
        arguments = dict(locals())
        policy_kwargs = off_policy_kwargs(policy_kwargs, arguments)
        super().__init__(policy, env, policy_kwargs=policy_kwargs, _init_setup_model=False, **kwargs)
        for name in (*SNAPSHOT_ARGUMENTS, "live_encoder_gradient", "flush_denormal"):
            setattr(self, name, arguments[name])
        self._check_arguments()
        self._history_credit = 0
        self._snapshot_episodes = 0  # SB3's episode count at the latest snapshot
        if _init_setup_model:
            self._setup_model()

    def _check_arguments(self) -> None:
        """The snapshot arguments and the flags as the model holds them (given to the constructor, or to ``load``):
        a ValueError names the first bad one."""
        check_snapshot_arguments({name: getattr(self, name) for name in SNAPSHOT_ARGUMENTS})
        for name in SNAPSHOT_ARGUMENTS:
            setattr(self, name, int(getattr(self, name)))
        for name in ("live_encoder_gradient", "flush_denormal"):
            if not isinstance(getattr(self, name), bool):
                raise ValueError(f"{name} must be a bool, got {getattr(self, name)!r}")

    def _setup_model(self) -> None:
        check_policy_class(self, self.policy_aliases["MlpPolicy"])  # the algorithm's PeVFA policy class
        self._check_arguments()  # again: load() sets its keyword arguments on the model before this
        super()._setup_model()
        critic = self.policy.critic
        for module in (critic, self.policy.critic_target):
            module.live_chi_gradient = self.live_encoder_gradient
        self.history = PolicyHistory(
            self.observation_space,
            self.action_space,
            critic.layout.n_params,
            n_state_action_pairs=critic.pair_states.shape[0],
            code_dim=critic.behaviour_codes.numel(),
            buffer_size=1,  # records only: the replay buffer holds the transitions
            max_policies=self.history_max_policies,
            seed=self.seed,
            representation=self.policy.representation_name,
            layout=critic.layout,
        )

    def _setup_learn(
        self,
        total_timesteps: int,
        callback: Any = None,
        reset_num_timesteps: bool = True,
        tb_log_name: str = "run",
        progress_bar: bool = False,
    ) -> tuple[int, Any]:
        self._require_env()
        if reset_num_timesteps:  # SB3 counts the episodes anew
            self._snapshot_episodes = 0
        elif self._n_updates and self.history_train_freq and not self.history.n_policies:  # they travel with the buffer
            warnings.warn(
                f"{type(self).__name__} learns on from {self.num_timesteps} steps ({self._n_updates} updates) without "
                "its snapshots: load_replay_buffer (or load_history) brings those saved with save_replay_buffer",
                stacklevel=4,  # the user's learn (SAC.learn, OffPolicyAlgorithm.learn, this)
            )
        return super()._setup_learn(total_timesteps, callback, reset_num_timesteps, tb_log_name, progress_bar)

    def _excluded_save_params(self) -> list[str]:
        return [*super()._excluded_save_params(), "history"]

    # ------------------------------------------------------------------ snapshots
    def _replay_states(self, n: int, evenly: bool = False) -> th.Tensor:
        """``n`` replay observations as the actor reads them (normalised where a VecNormalize is), flattened: drawn
        uniformly, or ``evenly`` spaced over those stored so far (the fingerprint's probes, no random draw)."""
        buffer = self.replay_buffer
        if not evenly:
            observations = buffer.sample(n, env=self._vec_normalize_env).observations  # type: ignore[union-attr]
        else:
            stored = buffer.buffer_size if buffer.full else buffer.pos  # type: ignore[union-attr]
            index = np.arange(n) * stored // n
            raw = rows(buffer.observations, (index, index % buffer.n_envs))  # type: ignore[union-attr]
            observations = obs_as_tensor(buffer._normalize_obs(raw, self._vec_normalize_env), self.device)  # type: ignore[union-attr]
        with th.no_grad():
            return self.actor.extract_features(observations, self.actor.features_extractor)

    def record_snapshot(self) -> int:
        """Record the live actor (its flat parameters; its actions at replay states for ``spr``; a random code) and make
        its states and code the critics'; its id. The first one also sets the fingerprint's probe states. The previous
        snapshot's ``episode_return`` (history's ``record_info``) becomes the mean return of the episodes that ended
        since it was recorded (while the buffer of SB3's episode infos still holds them all)."""
        critic, target = self.policy.critic, self.policy.critic_target
        rows = critic.representation.rollout_rows(self.replay_buffer.size())  # type: ignore[union-attr]
        if rows is not None:  # the fingerprint's probes, once: evenly spaced replay states
            features = self._replay_states(len(rows), evenly=True)
            for module in (critic, target):
                module.representation.observe_rollout(features)
        states = self._replay_states(self.history.n_state_action_pairs) if self.history.n_state_action_pairs else None
        with th.no_grad():
            for module in (critic, target):
                if states is not None:
                    module.pair_states.copy_(states)
        record = {
            "params": critic.layout.flatten(self.policy).cpu().numpy(),
            "codes": self.history.rng.uniform(-1.0, 1.0, size=self.history.code_dim).astype(np.float32),
            "states": np.zeros((0, state_dim(self.observation_space)), np.float32),
            "actions": np.zeros((0, get_action_dim(self.action_space)), np.float32),
        }
        if states is not None:
            record.update(states=states.cpu().numpy(), actions=critic.actor_actions(states).cpu().numpy())
        previous = self.history.latest_policy_id
        ended = self._episode_num - self._snapshot_episodes  # episodes that ended since the previous snapshot
        if previous is not None and 0 < ended <= len(self.ep_info_buffer):
            returns = [info["r"] for info in list(self.ep_info_buffer)[-ended:]]
            self.history.update_record_info(previous, episode_return=float(np.mean(returns)))
        self._snapshot_episodes = self._episode_num
        policy_id = self.history.add_record(record, n_updates=self._n_updates, num_timesteps=self.num_timesteps)
        with th.no_grad():
            for module in (critic, target):
                module.behaviour_codes.copy_(th.as_tensor(record["codes"]))
        return policy_id

    def train(self, gradient_steps: int, batch_size: int = 64) -> None:
        """SB3's update with a snapshot every ``snapshot_freq`` of its ``gradient_steps``, then the snapshots' critic
        updates of those steps, float32 denormals flushed to zero unless ``flush_denormal`` is False
        (:mod:`~sb3_pevfa.pevfa.denormals`)."""
        with flush_denormals(self.flush_denormal):
            self._train(gradient_steps, batch_size)

    def _train(self, gradient_steps: int, batch_size: int) -> None:
        remaining, pieces = gradient_steps, []
        while remaining > 0:  # SB3's update, in pieces that end where a snapshot is due
            steps = min(remaining, self.snapshot_freq - self._n_updates % self.snapshot_freq)
            super().train(steps, batch_size)  # type: ignore[safe-super]
            remaining -= steps
            pieces.append((steps, self._popped_means()))
            if not self.history.n_policies or self._n_updates % self.snapshot_freq == 0:
                self.record_snapshot()
        for key in dict.fromkeys(key for _, means in pieces for key in means):  # SB3's means over the whole call
            logged = [(steps, means[key]) for steps, means in pieces if key in means]
            total = sum(steps for steps, _ in logged)
            self.logger.record(key, logged[0][1] if len(logged) == 1 else sum(n * v for n, v in logged) / total)
        if self.history_train_freq == 0 or self.num_timesteps < self.history_learning_starts:
            return
        self._history_credit += gradient_steps
        n_updates, self._history_credit = divmod(self._history_credit, self.history_train_freq)
        losses = [self._train_on_snapshots() for _ in range(n_updates)]
        if losses:
            live, target = (getattr(self, name) for name in self.critic_norm_stats)
            polyak_update(live, target, 1.0)  # the targets' BatchNorm statistics, as SB3 copies them at each update
            self.logger.record("pevfa/history_value_loss", float(np.mean(losses)))
        self._n_history_updates += len(losses)
        self.logger.record("pevfa/n_history_updates", self._n_history_updates)  # so far, as SB3's train/n_updates
        self.logger.record("pevfa/n_policies", self.history.n_policies)

    def _popped_means(self) -> dict[str, float]:
        """The means SB3's update just logged (``train/critic_loss``, ...; not its counts and learning rate), taken
        from the logger to be recorded once for the whole ``train`` call, weighted by each piece's gradient steps."""
        values = self.logger.name_to_value
        keys = [key for key in values if key.startswith("train/") and key not in ("train/n_updates", "train/learning_rate")]
        return {key: values.pop(key) for key in keys}

    def _snapshot_actions(self, records: PolicyRecord, features: th.Tensor) -> tuple[th.Tensor, th.Tensor | None]:
        """Actions of ``P`` snapshots at their own inputs ``(P, K, features)``: ``(P * K, action_dim)`` and their
        log-probabilities ``(P * K,)`` (None for deterministic actors)."""
        raise NotImplementedError

    def _live_next_actions(self, observations: th.Tensor) -> tuple[th.Tensor, th.Tensor | None]:
        """The actions of SB3's target for next observations (SAC: the live actor's, with their log-probabilities;
        TD3: the target actor's, smoothed), as a conventional critic beside the run trains on them."""
        raise NotImplementedError

    def _entropy_term(self) -> th.Tensor | None:
        """alpha of the target's entropy term (None: no entropy term)."""
        return None

    def _train_on_snapshots(self) -> float:
        """One critic update of Q(s, a, chi_k) on replay transitions paired with snapshots k; its loss."""
        critic, target = self.policy.critic, self.policy.critic_target
        ids = self.history.sample_policy_ids(self.history_batch_policies)
        n_policies = len(ids)
        per_policy = self.history_batch_size // self.history_batch_policies
        data = self.replay_buffer.sample(per_policy * n_policies, env=self._vec_normalize_env)  # type: ignore[union-attr]
        if isinstance(self.replay_buffer, HerReplayBuffer):  # its real transitions come first, the relabelled last
            data = shuffled(data)
        records = PolicyRecord.from_numpy(self.history.records(ids), self.device)
        pairing = th.arange(n_policies, device=self.device).repeat_interleave(per_policy)  # snapshot of each transition
        with th.no_grad():
            extractor = self.actor.features_extractor
            extractor.train(False)  # the live actor's features, without moving its statistics (BatchNorm, dropout)
            features = self.actor.extract_features(data.next_observations, extractor)
            extractor.train(self.actor.training)
            actions, log_prob = self._snapshot_actions(records, features.reshape(n_policies, per_policy, -1))
            next_values = target(data.next_observations, actions, target.representation(records), pairing)
            targets = self.td_targets(data, next_values, log_prob)
        values = critic(data.observations, data.actions, critic.representation(records), pairing)
        return self.fit_critic(values, targets, critic.optimizer)

    def td_targets(self, data: Any, next_values: tuple[th.Tensor, ...], log_prob: th.Tensor | None) -> th.Tensor:
        """SB3's targets r + gamma (1 - d) (min_i Q'_i(s', a') [- alpha log pi(a' | s')]) of replay ``data`` from the
        target critics' values at the next actions (and the actions' log-probabilities: SAC)."""
        discounts = getattr(data, "discounts", None)  # SB3 >= 2.7's n-step returns
        discounts = self.gamma if discounts is None else discounts
        next_q, _ = th.min(th.cat(next_values, dim=1), dim=1, keepdim=True)
        alpha = self._entropy_term()
        if alpha is not None and log_prob is not None:
            next_q = next_q - alpha * log_prob.reshape(-1, 1)
        return data.rewards + (1 - data.dones) * discounts * next_q

    def fit_critic(self, values: tuple[th.Tensor, ...], targets: th.Tensor, optimizer: th.optim.Optimizer) -> float:
        """One step of ``optimizer`` on SB3's critic loss (``critic_loss_scale`` times the critics' summed MSE); the
        loss."""
        loss = self.critic_loss_scale * sum(F.mse_loss(value, targets) for value in values)
        optimizer.zero_grad()
        loss.backward()  # type: ignore[union-attr]
        optimizer.step()
        return float(loss.item())  # type: ignore[union-attr]

    # ------------------------------------------------------------------ files
    def save_history(self, path: str | pathlib.Path | io.IOBase) -> None:
        """Save the snapshots (``.npz``, apart from the model, as the replay buffer is)."""
        self.history.save(path)

    def save_replay_buffer(self, path: str | pathlib.Path | io.BufferedIOBase) -> None:
        """SB3's, and the snapshots beside a file path (:func:`snapshots_path`): what rl-zoo3's
        ``--save-replay-buffer`` and SB3's ``CheckpointCallback(save_replay_buffer=True)`` save then travels whole.
        Both files are written before either replaces what was there: a failed save leaves the previous pair. A file
        object gets the buffer alone (with a warning where there are snapshots: :meth:`save_history` saves them)."""
        if isinstance(path, (str, pathlib.Path)) and with_default_suffix(path, "pkl").is_dir():
            raise ValueError(f"{with_default_suffix(path, 'pkl')} is a folder: save_replay_buffer takes a file path")
        if not isinstance(path, (str, pathlib.Path)):
            if self.history.n_policies:  # snapshots to lose
                warnings.warn(
                    f"{type(self).__name__}.save_replay_buffer saves the snapshots beside a file path only: save them with "
                    "save_history (a file object gets the replay buffer alone)",
                    stacklevel=2,
                )
            super().save_replay_buffer(path)
            return
        with replacing(with_default_suffix(path, "pkl")) as buffer, replacing(snapshots_path(path)) as snapshots:
            super().save_replay_buffer(buffer)
            self.save_history(snapshots)

    def load_replay_buffer(self, path: str | pathlib.Path | io.BufferedIOBase, truncate_last_traj: bool = True) -> None:
        """SB3's, and the snapshots saved beside it by :meth:`save_replay_buffer`, where they are (rl-zoo3's ``-i``).
        Where either fails, the model keeps its own. rl-zoo3 asks for the run's final ``replay_buffer.pkl`` also for a
        checkpoint: a replay buffer saved beside it at this model's ``num_timesteps`` (SB3's ``CheckpointCallback``
        with ``save_replay_buffer=True``) is loaded instead; snapshots from after it load with a warning."""
        path = path_of_the_moment(path, self.num_timesteps, "the replay buffer and snapshots", snapshots_path)
        had, previous = "replay_buffer" in vars(self), vars(self).get("replay_buffer")  # SB3's HER test deletes it first
        try:
            super().load_replay_buffer(path, truncate_last_traj)  # SB3 sets the buffer before it checks it
            self._check_replay_buffer(path)
            if isinstance(path, (str, pathlib.Path)) and snapshots_path(path).exists():
                self.load_history(snapshots_path(path))  # checked in full before it replaces anything
        except BaseException:
            if had:
                self.replay_buffer = previous
            else:
                vars(self).pop("replay_buffer", None)
            raise

    def _check_replay_buffer(self, path: Any) -> None:
        """A ValueError where the loaded replay buffer holds observations or actions of other shapes than the
        model's (SB3 takes it, and the first transition stored fails)."""
        buffer = self.replay_buffer
        found = (getattr(buffer, "obs_shape", None), getattr(buffer, "action_dim", None))
        expected = (get_obs_shape(self.observation_space), get_action_dim(self.action_space))
        if found != expected:
            if isinstance(path, (str, pathlib.Path)) and not pathlib.Path(path).exists():
                path = f"{path}.pkl"  # the file SB3 read
            raise ValueError(
                f"The replay buffer in {path} holds observations of shape {found[0]} and actions of size {found[1]}; "
                f"this model's are {expected[0]} and {expected[1]}"
            )

    def load_history(self, path: str | pathlib.Path | io.IOBase) -> None:
        """Load snapshots saved by :meth:`save_history`; the live actor's code and states become the latest
        snapshot's. Snapshots recorded after this model's ``num_timesteps`` load with a warning."""
        self.history.load(path)
        warn_if_newer(self.history, self.num_timesteps, path)
        latest = self.history.latest_policy_id
        if latest is not None:
            record = self.history.records([latest], fields=("codes", "states"))
            with th.no_grad():
                for module in (self.policy.critic, self.policy.critic_target):
                    module.behaviour_codes.copy_(th.as_tensor(record["codes"][0]))
                    module.pair_states.copy_(th.as_tensor(record["states"][0]))
