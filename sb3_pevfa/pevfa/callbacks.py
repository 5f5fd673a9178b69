"""A callback that keeps a policy history of a plain SB3 on-policy actor-critic run (PPO, A2C), for analysis."""

from stable_baselines3.common.callbacks import BaseCallback
from stable_baselines3.common.policies import ActorCriticPolicy

from sb3_pevfa.pevfa.history import PolicyHistory
from sb3_pevfa.pevfa.recorder import PolicyRecorder
from sb3_pevfa.pevfa.records import ActorLayout, has_image, rows


class PolicyHistoryCallback(BaseCallback):
    """Record the policy of every rollout, its samples and the final policy in a :class:`PolicyHistory`.

    A thin adapter of :class:`~sb3_pevfa.pevfa.recorder.PolicyRecorder` on SB3's callback hooks: at the end of each
    rollout the policy that collected it (not updated yet) is recorded and its samples appended; at the end of
    training the final policy is recorded. PeVFA algorithms record by themselves and need no callback. A2C updates
    every ``n_steps`` (5 by default), so it records many more policies than PPO: lower ``n_state_action_pairs`` or
    ``max_policies`` to bound the memory.

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
        layout = ActorLayout.from_policy(policy)
        if self.history is None:
            self.history = PolicyHistory(
                policy.observation_space,
                policy.action_space,
                layout.n_params,
                n_state_action_pairs=0 if has_image(policy.observation_space) else self.n_state_action_pairs,
                buffer_size=self.buffer_size,
                max_policies=self.max_policies,
                seed=self.model.seed,
                layout=layout,
            )
        elif self.history.n_params != layout.n_params:
            raise ValueError(
                f"History stores {self.history.n_params} actor parameters, the model's actor has {layout.n_params}"
            )
        self.recorder = PolicyRecorder(self.history, layout)

    def _on_step(self) -> bool:
        self._episode_returns.extend(info["episode"]["r"] for info in self.locals.get("infos", ()) if "episode" in info)
        return True

    def _on_rollout_end(self) -> None:
        buffer = self.model.rollout_buffer
        first_obs = rows(buffer.observations, 0)  # the envs' observations when the rollout started
        start = self.model.num_timesteps - buffer.buffer_size * buffer.n_envs
        policy_id = self.recorder.record(self.model.policy, first_obs, num_timesteps=start)
        self.recorder.add_rollout(buffer, policy_id, self._episode_returns)
        self._episode_returns = []

    def _on_training_end(self) -> None:
        observations = self.history.sample_observations(1)
        if observations is not None:
            self.recorder.record(self.model.policy, observations, num_timesteps=self.model.num_timesteps)
