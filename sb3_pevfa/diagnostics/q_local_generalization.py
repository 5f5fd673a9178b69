"""Local generalization of an off-policy PeVFA (paper Sec. 3.2, Fig. 3b / 8, adapted to Q): is Q(s, a, chi_k) of a
new snapshot k closer to the returns its actor then collected than a conventional Q(s, a) trained beside, before and
after the critics learn from those transitions?

A window is the stretch of a run between two snapshots of the actor: the transitions collected there come from
snapshot k's actor as it keeps learning (``snapshot_freq`` gradient steps). At its start both critics are frozen as
they are; at its end, the errors of the frozen critics ("before") and of the live ones ("after", chi still snapshot
k's) against the transitions' discounted returns are due. They are logged one window later, when the episodes begun
in the window have ended.
"""

import copy
import warnings

import numpy as np
import torch as th
from stable_baselines3.common.policies import ContinuousCritic
from stable_baselines3.common.utils import obs_as_tensor, polyak_update, update_learning_rate

from sb3_pevfa.diagnostics.local_generalization import ERROR_KEYS, ResumableDiagnostic
from sb3_pevfa.pevfa.off_policy import OffPolicyPeVFA
from sb3_pevfa.pevfa.records import PolicyRecord


def soft_monte_carlo_returns(
    rewards: np.ndarray, ends: np.ndarray, terminal: np.ndarray, bonuses: np.ndarray, gamma: float
) -> tuple[np.ndarray, np.ndarray]:
    """Discounted returns of replay rows ``(n_rows, n_envs)`` in time order, with SAC's entropy bonus:
    G_t = r_t + gamma (G_{t+1} - b_{t+1}) inside an episode, where b = alpha log pi(a | s) of the action taken
    (0 for TD3), and the discounted weight of what each return misses: 0 where its episode terminated, gamma^(k+1)
    where it was truncated (or is still open at the last row) k rows later.

    :param ends: The episode ended at this row (terminated or truncated); :param terminal: it terminated
    """
    returns = np.zeros(rewards.shape, dtype=np.float64)
    missing = np.ones(rewards.shape, dtype=np.float64)
    next_return, next_missing = np.zeros(rewards.shape[1]), np.ones(rewards.shape[1])
    next_bonus = np.zeros(rewards.shape[1])
    for row in reversed(range(len(rewards))):
        going_on = ~ends[row].astype(bool)
        returns[row] = rewards[row] + gamma * going_on * (next_return - next_bonus)
        missing[row] = np.where(going_on, gamma * next_missing, np.where(terminal[row], 0.0, gamma))
        next_return, next_missing, next_bonus = returns[row], missing[row], bonuses[row]
    return returns, missing


class QLocalGeneralizationCallback(ResumableDiagnostic):
    """Trains a conventional twin critic Q(s, a) (SB3's, the model's critic layers, optimizer and learning rate)
    beside a :class:`~sb3_pevfa.SACPeVFA` or :class:`~sb3_pevfa.TD3PeVFA` run on its replay buffer with SB3's targets
    (one update per gradient step of the model, after them; Polyak targets with the model's ``tau``), and logs per
    window between two snapshots the mean squared error of min_i Q_i(s, a, chi_k) and of min_i Q_i(s, a) against the
    discounted returns (SAC: with its entropy bonus at the moment of acting) of the window's transitions, before and
    after the window: ``pevfa/local_gen/{pevfa_before, pevfa_after, vfa_before, vfa_after}`` (plus ``timesteps``,
    the window's end, and ``n_states``), the keys of the on-policy diagnostic, a logger row per window; ``results``
    keeps them too, with the window's snapshot's ``policy_id``.

    Scored: transitions whose return misses at most ``tail_weight`` of discounted value (their episode terminated, or
    went on long enough after them, within the window and the next one). The conventional critic's updates and the
    log-probabilities draw random numbers: a run with the callback is another run than one without.
    ``state_dict`` / ``load_state_dict`` carry the conventional critic over a checkpoint (``ResumableDiagnostic``;
    the windows not scored yet are lost, and the resumed run's first window opens at its next snapshot).

    :param tail_weight: The largest discounted weight of the unknown rest of a scored return (0.01: a return whose
        episode was truncated at least 459 steps later at gamma 0.99)
    """

    saved_attributes = ("critic", "critic_target", "optimizer")

    def __init__(self, tail_weight: float = 0.01, verbose: int = 0):
        super().__init__(verbose)
        if not 0.0 <= tail_weight < 1.0:
            raise ValueError(f"tail_weight must be in [0, 1), got {tail_weight}")
        self.tail_weight = tail_weight
        self._window: dict | None = None
        self._closed: dict | None = None
        self._warned_unscored = False

    def _init_callback(self) -> None:
        model = self.model
        if not isinstance(model, OffPolicyPeVFA):
            raise TypeError(f"QLocalGeneralizationCallback needs a SACPeVFA or TD3PeVFA model, got {type(model).__name__}")
        #: Windows open at the next snapshot recorded from now (one recorded before would have trained the critics on
        #: its transitions already)
        self._waiting_for = model.history.latest_policy_id
        self._updates = model._n_updates  # the model's updates from now on (a learn() without the callback: not owed)
        super()._init_callback()

    def _build_critic(self) -> None:
        model, policy = self.model, self.model.policy
        self.critic = ContinuousCritic(**policy._update_features_extractor(policy.critic_kwargs, None)).to(model.device)
        self.critic_target = copy.deepcopy(self.critic).train(False)
        self.optimizer = policy.optimizer_class(self.critic.parameters(), lr=model.lr_schedule(1), **policy.optimizer_kwargs)
        buffer = model.replay_buffer
        #: alpha log pi(a | s) of each replay row's action when it was taken (SAC)
        self.bonuses = np.zeros((buffer.buffer_size, buffer.n_envs), dtype=np.float32)
        self._rows_added = 0  # transitions (rows of the replay buffer) since the callback began

    # ------------------------------------------------------------------ the conventional critic
    def _catch_up(self) -> None:
        """The conventional critic's updates for the model's since the last call, with SB3's schedule of target
        updates: TD3 after every ``policy_delay``-th update of the model, SAC at every ``target_update_interval``-th
        gradient step of a ``train`` call (the updates since the last call are one ``train`` call's)."""
        model = self.model
        for step in range(model._n_updates - self._updates):
            if hasattr(model, "policy_delay"):
                polyak = (self._updates + step + 1) % model.policy_delay == 0
            else:
                polyak = step % model.target_update_interval == 0
            self._train_critic(polyak)
        self._updates = model._n_updates

    def _train_critic(self, polyak: bool = True) -> None:
        """One update of the conventional critic as SB3's update fits its own (SAC / TD3 targets of the live actor),
        then its target's Polyak update where ``polyak``."""
        model = self.model
        update_learning_rate(self.optimizer, model.lr_schedule(model._current_progress_remaining))
        data = model.replay_buffer.sample(model.batch_size, env=model._vec_normalize_env)
        with th.no_grad():
            next_actions, next_log_prob = model._live_next_actions(data.next_observations)
            targets = model.td_targets(data, self.critic_target(data.next_observations, next_actions), next_log_prob)
        model.fit_critic(self.critic(data.observations, data.actions), targets, self.optimizer)
        if polyak:
            polyak_update(self.critic.parameters(), self.critic_target.parameters(), model.tau)

    # ------------------------------------------------------------------ hooks
    def _on_step(self) -> bool:
        """Keep alpha log pi of the action just taken (its replay row is the buffer's position)."""
        model = self.model
        alpha = model._entropy_term()
        if alpha is not None and self._window is not None:
            actor = model.actor
            with th.no_grad():
                observations = obs_as_tensor(model._last_obs, model.device)
                mean, log_std, kwargs = actor.get_action_dist_params(observations)
                distribution = actor.action_dist.proba_distribution(mean, log_std, **kwargs)
                actions = th.as_tensor(self.locals["buffer_actions"], device=model.device, dtype=th.float32)
                log_prob = distribution.log_prob(actions)
            self.bonuses[model.replay_buffer.pos] = (alpha * log_prob).cpu().numpy()
        self._rows_added += 1
        return True

    def _on_rollout_start(self) -> None:
        """After the model's update: the conventional critic's updates; where a snapshot was recorded, the window
        closes and the next one opens."""
        self._catch_up()
        latest = self.model.history.latest_policy_id
        opened = None if self._window is None else self._window["policy_id"]
        if latest is not None and latest not in (self._waiting_for, opened):
            self._close_window()
            self._open_window(latest)

    def _on_training_end(self) -> None:
        self._catch_up()
        self._close_window()
        self._score(self._closed)  # what its returns have by now
        self._closed = None

    # ------------------------------------------------------------------ windows
    def _open_window(self, policy_id: int) -> None:
        critic = self.model.policy.critic
        memo = {id(critic.actor_holder): critic.actor_holder, id(getattr(critic, "optimizer", None)): None}
        record = PolicyRecord.from_numpy(self.model.history.records([policy_id]), self.model.device)
        self._window = {
            "policy_id": policy_id,
            "record": record,  # kept: the history may drop the snapshot before the window is scored
            "start": self.model.replay_buffer.pos,
            "first_row": self._rows_added,
            "pevfa": copy.deepcopy(critic, memo).train(False),
            "vfa": copy.deepcopy(self.critic).train(False),
            "chi": self._chi(critic, record),
        }

    @staticmethod
    def _chi(critic, records: PolicyRecord) -> th.Tensor:
        """chi of a snapshot's record by ``critic``'s encoder (in evaluation mode)."""
        training = critic.representation.training
        critic.representation.train(False)
        with th.no_grad():
            chi = critic.representation(records)
        critic.representation.train(training)
        return chi

    def _rows(self, window: dict) -> np.ndarray | None:
        """The replay rows of the transitions since ``window`` opened (None where the buffer has overwritten some)."""
        size, count = self.model.replay_buffer.buffer_size, self._rows_added - window["first_row"]
        if count > size:
            warnings.warn(f"The replay buffer ({size} rows) overwrote transitions of a window: it is not scored", stacklevel=2)
            return None
        return (window["start"] + np.arange(count)) % size

    def _close_window(self) -> None:
        """Predictions of the window's transitions by its frozen and by the live critics; the previous window scored."""
        window, self._window = self._window, None
        if window is None:
            return
        self._score(self._closed)
        self._closed = None
        model, buffer = self.model, self.model.replay_buffer
        rows = self._rows(window)
        if rows is None:
            return
        n = rows.size * buffer.n_envs
        if isinstance(buffer.observations, dict):  # a DictReplayBuffer (MultiInputPolicy)
            raw = {key: value[rows].reshape(n, *buffer.obs_shape[key]) for key, value in buffer.observations.items()}
        else:
            raw = buffer.observations[rows].reshape(n, *buffer.obs_shape)
        observations = obs_as_tensor(buffer._normalize_obs(raw, model._vec_normalize_env), model.device)
        actions = th.as_tensor(buffer.actions[rows].reshape(n, -1), device=model.device)
        live = model.policy.critic
        training = live.training
        live.train(False)
        chi = self._chi(live, window["record"])
        with th.no_grad():
            predictions = {
                "pevfa_before": window["pevfa"](observations, actions, window["chi"]),
                "pevfa_after": live(observations, actions, chi),
                "vfa_before": window["vfa"](observations, actions),
                "vfa_after": self.critic(observations, actions),
            }
        live.train(training)
        self._closed = {
            "start": window["start"],
            "first_row": window["first_row"],
            "policy_id": window["policy_id"],
            "n_rows": rows.size,
            "timesteps": model.num_timesteps,
            **{key: th.min(th.cat(values, dim=1), dim=1)[0].cpu().numpy() for key, values in predictions.items()},
        }

    def _score(self, closed: dict | None) -> None:
        """Log the errors of a closed window against the returns of its transitions, as complete as they are now."""
        if closed is None or closed["n_rows"] == 0:
            return
        model, buffer = self.model, self.model.replay_buffer
        rows = self._rows(closed)
        if rows is None:
            return
        rewards = buffer._normalize_reward(buffer.rewards[rows], model._vec_normalize_env)
        ends = buffer.dones[rows].astype(bool)
        terminal = ends & ~buffer.timeouts[rows].astype(bool) if buffer.handle_timeout_termination else ends
        returns, missing = soft_monte_carlo_returns(rewards, ends, terminal, self.bonuses[rows], model.gamma)
        scored = (missing <= self.tail_weight)[: closed["n_rows"]].reshape(-1)
        target = returns[: closed["n_rows"]].reshape(-1)[scored]
        errors = {key: float(np.mean((closed[key][scored] - target) ** 2)) if scored.any() else np.nan for key in ERROR_KEYS}
        if not scored.any() and not self._warned_unscored:
            self._warned_unscored = True
            steps = int(np.ceil(np.log(self.tail_weight) / np.log(model.gamma))) if self.tail_weight > 0 else 0
            went_on = f", or went on {steps} steps after it" if steps else ""
            warnings.warn(
                f"No transition of a window ({closed['n_rows']} rows) is scored: none has a return that misses at most "
                f"tail_weight={self.tail_weight} of its discounted value (its episode terminated{went_on}). Episodes "
                "that end at a shorter time limit are never scored: use an env whose episodes "
                "terminate, a longer time limit, a lower gamma or a larger tail_weight",
                stacklevel=2,
            )
        self.results.append({**errors, "timesteps": closed["timesteps"], "n_states": int(scored.sum()),
                             "policy_id": closed["policy_id"]})  # fmt: skip
        for key, value in self.results[-1].items():
            self.logger.record(f"pevfa/local_gen/{key}", value)
        self.logger.dump(self.num_timesteps)  # a row per window (SB3 dumps its own every few episodes)
