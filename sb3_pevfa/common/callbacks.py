"""Callback that records a policy history during any SB3 on-policy actor-critic run (PPO, A2C, PPOPeVFA)."""

import numpy as np
from stable_baselines3.common.callbacks import BaseCallback
from stable_baselines3.common.policies import ActorCriticPolicy

from sb3_pevfa.common.history import PolicyHistory
from sb3_pevfa.common.policy_data import ActorLayout, PolicyData, has_image, snapshot_policy


class PolicyHistoryCallback(BaseCallback):
    """Snapshot the policy at every update and store its rollout samples in a :class:`PolicyHistory`.

    At the start of each rollout the live policy is recorded (flat actor parameters, actions sampled at
    ``n_state_action_pairs`` probe states drawn from the history, and a random code if the history has one),
    unless it is unchanged since the last record. At the end of the rollout its ``(observation, value target)``
    samples are appended, tagged with its id, and the mean return of the episodes that ended during the rollout
    (from SB3's Monitor) is kept as the policy's ``episode_return``. At the end of training the final policy is
    recorded too.

    :class:`~sb3_pevfa.PPOPeVFA` installs one itself; attach one to a plain PPO/A2C run to keep a policy
    history for later analysis (``callback.history.save(path)``). A2C updates every ``n_steps`` (5 by default), so
    it records many more policies than PPO: lower ``n_state_action_pairs`` or ``max_policies`` to bound the memory.

    :param history: Where to record; by default a new one is built from the model's spaces
    :param n_state_action_pairs: Pairs per policy when building the history (0 with image observations)
    :param buffer_size: Sample bound when building the history
    :param max_policies: Policy bound when building the history
    """

    def __init__(
        self,
        history: PolicyHistory | None = None,
        n_state_action_pairs: int = 200,
        buffer_size: int = 200_000,
        max_policies: int = 10_000,
        verbose: int = 0,
    ):
        super().__init__(verbose)
        self.history = history
        self.n_state_action_pairs = n_state_action_pairs
        self.buffer_size = buffer_size
        self.max_policies = max_policies
        self._episode_returns: list[float] = []

    def _init_callback(self) -> None:
        policy = self.model.policy
        if not isinstance(policy, ActorCriticPolicy):
            raise TypeError(f"PolicyHistoryCallback needs an ActorCriticPolicy, got {type(policy).__name__}")
        self.layout = ActorLayout.from_policy(policy)
        if self.history is None:
            n_pairs = 0 if has_image(policy.observation_space) else self.n_state_action_pairs
            self.history = PolicyHistory(
                policy.observation_space,
                policy.action_space,
                self.layout.n_params,
                n_state_action_pairs=n_pairs,
                buffer_size=self.buffer_size,
                max_policies=self.max_policies,
                seed=self.model.seed,
            )
        elif self.history.n_params != self.layout.n_params:
            raise ValueError(
                f"History stores {self.history.n_params} actor parameters, the model's actor has {self.layout.n_params}"
            )

    def _probe_observations(self):
        n_pairs = self.history.n_state_action_pairs
        if n_pairs == 0:
            return None
        observations = self.history.sample_observations(n_pairs)
        if observations is not None:
            return observations
        # Nothing recorded yet (first policy): probe at the environments' current observations.
        last_obs = self.model._last_obs
        index = self.history.rng.integers(self.model.n_envs, size=n_pairs)
        if isinstance(last_obs, dict):
            return {key: value[index] for key, value in last_obs.items()}
        return last_obs[index]  # type: ignore[index]

    def record_policy(self) -> int:
        """Record the live policy unless it is already the latest record; returns its id and hands the record
        to PeVFA policies, whose critic then evaluates this policy."""
        history, policy = self.history, self.model.policy
        latest = history.latest_policy_id
        params = self.layout.flatten(policy).cpu().numpy()
        if latest is None or not np.array_equal(history.policy_data([latest])["params"][0], params):
            code = history.rng.uniform(-1.0, 1.0, size=history.code_dim)
            record = snapshot_policy(policy, self.layout, self._probe_observations(), code)
            latest = history.add_policy(record, n_updates=self.model._n_updates, num_timesteps=self.model.num_timesteps)
        if hasattr(policy, "set_behaviour_policy"):
            policy.set_behaviour_policy(PolicyData.from_numpy(history.policy_data([latest]), policy.device))
        return latest

    def _on_rollout_start(self) -> None:
        self.record_policy()
        self._episode_returns = []

    def _on_step(self) -> bool:
        self._episode_returns.extend(info["episode"]["r"] for info in self.locals.get("infos", ()) if "episode" in info)
        return True

    def _on_rollout_end(self) -> None:
        buffer = self.model.rollout_buffer
        policy_id = self.history.latest_policy_id
        self.history.add_samples(buffer.observations, buffer.returns, policy_id)
        if self._episode_returns:  # episodes (Monitor) that ended during this policy's rollout
            self.history.update_policy_info(policy_id, episode_return=float(np.mean(self._episode_returns)))
        self._episode_returns = []

    def _on_training_end(self) -> None:
        self.record_policy()
