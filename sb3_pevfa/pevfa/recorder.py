"""The recorder: one record per policy update into a :class:`~sb3_pevfa.pevfa.history.PolicyHistory`."""

import numpy as np
from stable_baselines3.common.buffers import RolloutBuffer
from stable_baselines3.common.policies import ActorCriticPolicy

from sb3_pevfa.pevfa.history import ObsBatch, PolicyHistory
from sb3_pevfa.pevfa.normalization import RolloutRecorder
from sb3_pevfa.pevfa.records import ActorLayout, batch_size, flat_states, record_policy, rows


class PolicyRecorder:
    """Records each policy once, before it acts, and then the ``(observation, value target)`` samples it collected.

    A record holds the actor's flat parameters, the actions it samples at ``n_state_action_pairs`` probe states
    drawn from the history (SPR's pairs) and a random code (``random`` representation); see
    :func:`~sb3_pevfa.pevfa.records.record_policy`.

    :param history: Where records and samples go
    :param layout: The actor's parameter layout
    """

    def __init__(self, history: PolicyHistory, layout: ActorLayout):
        self.history = history
        self.layout = layout

    def _probe_observations(self, fallback: ObsBatch) -> ObsBatch | None:
        """Probe states as stored (raw under ``renormalize``)."""
        n_pairs = self.history.n_state_action_pairs
        if n_pairs == 0:
            return None
        observations = self.history.sample_observations(n_pairs, raw=True)
        if observations is not None:
            return observations
        # Nothing recorded yet (first policy): probe at the fallback observations (the envs' current ones).
        return rows(fallback, self.history.rng.integers(batch_size(fallback), size=n_pairs))

    def record(self, policy: ActorCriticPolicy, fallback_obs: ObsBatch, **info: int | float) -> int:
        """Record ``policy`` unless it equals the latest record; returns the id of its record.

        :param fallback_obs: Observations to probe at while the history holds no sample (the first policy); raw
            under the history's ``renormalize``
        :param info: Numbers kept with a new record (``record_info``), e.g. ``num_timesteps``
        """
        history = self.history
        latest = history.latest_policy_id
        params = self.layout.flatten(policy).cpu().numpy()
        # an unchanged policy is recorded once; with transitions, each rollout needs a record of its own (its bootstrap)
        reusable = latest is not None and not (history.transitions and history.sample_count(latest))
        if not reusable or not np.array_equal(history.records([latest], fields=("params",))["params"][0], params):
            code = history.rng.uniform(-1.0, 1.0, size=history.code_dim)
            probes = self._probe_observations(fallback_obs)
            # the policy acts at the probes in today's statistics; the record keeps them raw where it can
            record = record_policy(policy, self.layout, None if probes is None else history.normalized(probes), code)
            if probes is not None and history.raw_states:
                record["states"] = flat_states(probes, policy.observation_space)
            latest = history.add_record(record, **info)
        return latest

    def add_rollout(
        self,
        buffer: RolloutBuffer,
        policy_id: int,
        episode_returns: list[float],
        last_obs: ObsBatch | None = None,
        last_episode_starts: np.ndarray | None = None,
        raw: RolloutRecorder | None = None,
    ) -> None:
        """Append the rollout's samples (observations and value targets) for the policy that collected them, and the
        mean return of the episodes that ended during it (``episode_return``). A history that keeps transitions also
        gets the rewards, episode starts and the observations after the rollout (``last_obs``).

        :param raw: The rollout's raw observations, rewards and reward scales (for a history with ``renormalize``)"""
        observations, extra = buffer.observations, {}
        if self.history.renormalize:
            assert raw is not None, "a history that renormalizes needs the rollout's raw data"
            observations, last_obs, raw_rewards, scales = raw.stacked()
            extra["reward_scales"] = scales
            if self.history.transitions:
                # the rewards as VecNormalize gave them (float64 division, clip, float32): what SB3 added beyond them
                # is the time-limit bootstrap gamma * V(terminal observation), 0 elsewhere
                normalized_then = raw_rewards / scales
                if raw.env.norm_reward:
                    normalized_then = np.clip(normalized_then, -raw.env.clip_reward, raw.env.clip_reward)
                bootstraps = (buffer.rewards - normalized_then.astype(np.float32)) * scales
                extra.update(raw_rewards=raw_rewards, raw_bootstraps=bootstraps)
        if self.history.transitions:
            extra.update(
                rewards=buffer.rewards,
                episode_starts=buffer.episode_starts,
                last_observations=last_obs,
                last_episode_starts=last_episode_starts,
            )
        self.history.add_samples(observations, buffer.returns, policy_id, **extra)
        if episode_returns:
            self.history.update_record_info(policy_id, episode_return=float(np.mean(episode_returns)))
