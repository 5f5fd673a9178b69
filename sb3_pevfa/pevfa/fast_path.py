"""The fast path (``fast_path=True``): SB3's rollout without the critic at every step.

Built from SB3's public pieces (the policy's ``get_distribution`` and ``predict_values``, SB3's distributions with
their argument checks), with SB3's math and random draws: results equal SB3's own path (``fast_path=False``) up to
float round-off (``tests/test_fast_path.py``). Only what profiling shows SB3 cannot do as fast is kept here
(docs/notes/2026-12-01-fast-path-redesign.md, ``docs/notes/scripts/fast_path.py``): the lean PPO update that was
here saved 4 % (Hopper-v5) and -1 % (CartPole-v1) of the update's CPU time, inside the noise of that measurement
(+-5 %), and was removed; both paths run SB3's own ``PPO.train`` / ``A2C.train``.

Per-step callbacks see SB3's locals except ``values`` and ``log_probs`` (not computed during the rollout).
"""

import numpy as np
import torch as th
from gymnasium import spaces
from stable_baselines3.common.buffers import DictRolloutBuffer, RolloutBuffer
from stable_baselines3.common.callbacks import BaseCallback
from stable_baselines3.common.on_policy_algorithm import OnPolicyAlgorithm
from stable_baselines3.common.policies import ActorCriticPolicy
from stable_baselines3.common.type_aliases import PyTorchObs
from stable_baselines3.common.utils import obs_as_tensor
from stable_baselines3.common.vec_env import VecEnv

from sb3_pevfa.pevfa.episodes import resize
from sb3_pevfa.pevfa.records import batch_size, rows, stack_observations

#: Observations per batched critic pass (bounds the memory of image rollouts)
VALUE_CHUNK = 4096


def flat_observations(buffer: RolloutBuffer | DictRolloutBuffer, device: th.device, env_major: bool) -> PyTorchObs:
    """The buffer's observations as one batch (``env_major``: SB3's training order), the buffer left as it is.

    Once SB3's ``RolloutBuffer.get`` has flattened the buffer in place (``generator_ready``), every field is one
    env-major batch already, and is returned as it is (in the same order as the buffer's other fields)."""

    def flat(array: np.ndarray) -> th.Tensor:
        if buffer.generator_ready:
            return th.as_tensor(array, device=device)
        array = array.swapaxes(0, 1) if env_major else array
        return th.as_tensor(array.reshape(-1, *array.shape[2:]), device=device)

    if isinstance(buffer.observations, dict):
        return {key: flat(obs) for key, obs in buffer.observations.items()}
    return flat(buffer.observations)


def predict_values(policy: ActorCriticPolicy, obs: PyTorchObs, chi: th.Tensor | None = None) -> th.Tensor:
    """Critic values of a large batch, in chunks of :data:`VALUE_CHUNK`, ``(batch,)``.

    :param chi: One embedding per observation ``(batch, embedding_dim)``; default: the behaviour policy's"""
    chunks = []
    with th.no_grad():
        for i in range(0, batch_size(obs), VALUE_CHUNK):
            part = slice(i, i + VALUE_CHUNK)
            extra = () if chi is None else (chi[part],)
            chunks.append(policy.predict_values(rows(obs, part), *extra))
    return th.cat(chunks).flatten()


def log_probabilities(policy: ActorCriticPolicy, obs: PyTorchObs, actions: np.ndarray) -> th.Tensor:
    """Log-probabilities of the actor's distribution at ``obs`` of the rollout's (stored) ``actions``, in chunks of
    :data:`VALUE_CHUNK`, ``(batch,)``: the numbers of SB3's per-step ``distribution.log_prob(actions)``, from one
    batched pass (the distribution depends only on the observation and the actor, which the rollout leaves alone)."""
    chunks = []
    with th.no_grad():
        for i in range(0, batch_size(obs), VALUE_CHUNK):
            part = slice(i, i + VALUE_CHUNK)
            # as SB3's PPO.train reads the buffer: float32 actions (the buffer keeps the space's dtype), Discrete as long
            batch = th.as_tensor(actions[part].astype(np.float32, copy=False), device=policy.device)
            if isinstance(policy.action_space, spaces.Discrete):
                batch = batch.long().flatten()
            chunks.append(policy.get_distribution(rows(obs, part)).log_prob(batch))
    return th.cat(chunks).flatten()


def collect_rollouts(
    model: OnPolicyAlgorithm,
    env: VecEnv,
    callback: BaseCallback,
    rollout_buffer: RolloutBuffer,
    n_rollout_steps: int,
) -> bool:
    """SB3's ``OnPolicyAlgorithm.collect_rollouts``, the actor alone acting, the critic evaluated after the rollout.

    Each step asks the policy for its action distribution only (``get_distribution``: actions, SB3's draws and
    checks); the values of the whole rollout, of the truncated episodes' last observations (bootstraps) and of the
    last observation come from one batched ``predict_values`` pass each, the log-probabilities of the rollout's
    actions from one batched ``get_distribution(...).log_prob`` pass (:func:`log_probabilities`).

    The model's rollout options shape it: ``rollout_episodes`` (iterations of whole episodes, one env:
    :mod:`~sb3_pevfa.pevfa.episodes`), ``bootstrap_truncated`` (False: an episode cut by a time limit ends as a
    terminal one, no bootstrap) and ``train_on_clipped_actions`` (the buffer keeps the actions the env received).

    Saves, measured (``docs/notes/scripts/fast_path.py``, CPU time of whole rollouts, median of 5, one torch thread):
    PPOPeVFA's 2048-step rollouts 23 % on Hopper-v5 (1.33 -> 1.03 ms per step) and 29 % on CartPole-v1
    (0.94 -> 0.67); A2CPeVFA's 5-step rollouts 3 % on Hopper-v5 and 11 % on CartPole-v1.
    """
    assert model._last_obs is not None, "No previous observation was provided"
    policy = model.policy
    policy.set_training_mode(False)
    n_steps = n_episodes = 0
    if getattr(model, "rollout_episodes", None) is not None:
        rollout_buffer.buffer_size = n_rollout_steps  # the last rollout's size, cut to what it collected
    rollout_buffer.reset()
    if model.use_sde:
        policy.reset_noise(env.num_envs)
    callback.on_rollout_start()
    no_values = th.zeros(env.num_envs)
    truncated: list[tuple[int, int, np.ndarray | dict]] = []  # (buffer position, env index, terminal observation)
    complete = False
    while not complete:
        if rollout_buffer.full:  # a rollout of whole episodes running past n_steps: room for another n_steps
            resize(rollout_buffer, rollout_buffer.buffer_size + n_rollout_steps)
        if model.use_sde and model.sde_sample_freq > 0 and n_steps % model.sde_sample_freq == 0:
            policy.reset_noise(env.num_envs)
        with th.no_grad():
            obs_tensor = obs_as_tensor(model._last_obs, model.device)  # type: ignore[arg-type]
            distribution = policy.get_distribution(obs_tensor)
            actions = distribution.get_actions()
        actions = actions.cpu().numpy().reshape((-1, *model.action_space.shape))  # type: ignore[misc]
        clipped_actions = actions
        if isinstance(model.action_space, spaces.Box):
            if policy.squash_output:
                clipped_actions = policy.unscale_action(clipped_actions)
            else:
                clipped_actions = np.clip(actions, model.action_space.low, model.action_space.high)
        new_obs, rewards, dones, infos = env.step(clipped_actions)
        model.num_timesteps += env.num_envs
        callback.update_locals(locals())
        if not callback.on_step():
            return False
        model._update_info_buffer(infos, dones)
        n_steps += 1
        if isinstance(model.action_space, spaces.Discrete):
            actions = actions.reshape(-1, 1)
        for idx, done in enumerate(dones):
            if done and infos[idx].get("terminal_observation") is not None and infos[idx].get("TimeLimit.truncated", False):
                truncated.append((rollout_buffer.pos, idx, infos[idx]["terminal_observation"]))
        stored = clipped_actions if getattr(model, "train_on_clipped_actions", False) else actions
        rollout_buffer.add(model._last_obs, stored, rewards, model._last_episode_starts, no_values, no_values)  # type: ignore[arg-type]
        model._last_obs = new_obs  # type: ignore[assignment]
        model._last_episode_starts = dones
        n_episodes += int(dones[0])
        complete = _rollout_complete(model, n_steps, n_rollout_steps, n_episodes, dones)
    if rollout_buffer.pos < rollout_buffer.buffer_size:
        resize(rollout_buffer, rollout_buffer.pos)
    _evaluate_rollout(model, rollout_buffer, truncated)
    with th.no_grad():
        values = policy.predict_values(obs_as_tensor(new_obs, model.device))  # type: ignore[arg-type]
    rollout_buffer.compute_returns_and_advantage(last_values=values, dones=dones)
    callback.update_locals(locals())
    callback.on_rollout_end()
    return True


def _rollout_complete(
    model: OnPolicyAlgorithm, n_steps: int, n_rollout_steps: int, n_episodes: int, dones: np.ndarray
) -> bool:
    """Whether the rollout ends with this step: after ``n_rollout_steps`` (SB3's), or with ``rollout_episodes``, at the
    first episode end after that many episodes or ``n_rollout_steps`` steps."""
    episodes = getattr(model, "rollout_episodes", None)
    if episodes is None:
        return n_steps >= n_rollout_steps
    return bool(dones[0]) and (n_episodes >= episodes or n_steps >= n_rollout_steps)


def _evaluate_rollout(
    model: OnPolicyAlgorithm, rollout_buffer: RolloutBuffer, truncated: list[tuple[int, int, np.ndarray | dict]]
) -> None:
    """The rollout's values and log-probabilities in batched passes, and the bootstraps of the episodes a time limit
    cut (SB3 #633; none with ``bootstrap_truncated=False``)."""
    policy = model.policy
    observations = flat_observations(rollout_buffer, model.device, env_major=False)
    values = predict_values(policy, observations)
    rollout_buffer.values[:] = values.cpu().numpy().reshape(rollout_buffer.values.shape)
    log_probs = log_probabilities(policy, observations, rollout_buffer.actions.reshape(-1, rollout_buffer.action_dim))
    rollout_buffer.log_probs[:] = log_probs.cpu().numpy().reshape(rollout_buffer.log_probs.shape)
    if truncated and getattr(model, "bootstrap_truncated", True):
        terminal_values = predict_values(
            policy, obs_as_tensor(stack_observations([obs for *_, obs in truncated]), model.device)
        )
        for (pos, idx, _), value in zip(truncated, terminal_values.cpu().numpy()):
            rollout_buffer.rewards[pos, idx] += model.gamma * value
