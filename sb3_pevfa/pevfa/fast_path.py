"""The fast path (``fast_path=True``): two of SB3's loops without work that PeVFA's critic makes expensive.

Built from SB3's and torch's public pieces (the policy's ``get_distribution``, ``predict_values`` and
``evaluate_actions``, SB3's distributions with their argument checks, ``torch.nn.utils.clip_grad_norm_``), with
SB3's math and random draws: results equal SB3's own path (``fast_path=False``) up to float round-off
(``tests/test_fast_path.py``). What each saves is measured by ``benchmarks/fast_path.py`` (docs/benchmarks.md).

Per-step callbacks see SB3's locals except ``values`` (not computed during the rollout).
"""

import numpy as np
import torch as th
from gymnasium import spaces
from stable_baselines3.common.buffers import DictRolloutBuffer, RolloutBuffer
from stable_baselines3.common.callbacks import BaseCallback
from stable_baselines3.common.on_policy_algorithm import OnPolicyAlgorithm
from stable_baselines3.common.policies import ActorCriticPolicy
from stable_baselines3.common.type_aliases import PyTorchObs
from stable_baselines3.common.utils import explained_variance, obs_as_tensor
from stable_baselines3.common.vec_env import VecEnv
from torch.nn import functional as F

#: Observations per batched critic pass (bounds the memory of image rollouts)
VALUE_CHUNK = 4096


def _stack(observations: list) -> np.ndarray | dict[str, np.ndarray]:
    if isinstance(observations[0], dict):
        return {key: np.stack([obs[key] for obs in observations]) for key in observations[0]}
    return np.stack(observations)


def rows(obs: PyTorchObs, index: slice | th.Tensor | np.ndarray) -> PyTorchObs:
    """The rows ``index`` of a batch of observations (a tensor or a dict of them)."""
    return {key: value[index] for key, value in obs.items()} if isinstance(obs, dict) else obs[index]


def flat_observations(buffer: RolloutBuffer | DictRolloutBuffer, device: th.device, env_major: bool) -> PyTorchObs:
    """The buffer's observations as one batch (``env_major``: SB3's training order), the buffer left as it is."""

    def flat(array: np.ndarray) -> th.Tensor:
        array = array.swapaxes(0, 1) if env_major else array
        return th.as_tensor(array.reshape(-1, *array.shape[2:]), device=device)

    if isinstance(buffer.observations, dict):
        return {key: flat(obs) for key, obs in buffer.observations.items()}
    return flat(buffer.observations)


def predict_values(policy: ActorCriticPolicy, obs: PyTorchObs) -> th.Tensor:
    """Critic values of a large batch, in chunks of :data:`VALUE_CHUNK`, ``(batch,)``."""
    n = len(next(iter(obs.values())) if isinstance(obs, dict) else obs)
    with th.no_grad():
        chunks = [policy.predict_values(rows(obs, slice(i, i + VALUE_CHUNK))) for i in range(0, n, VALUE_CHUNK)]
    return th.cat(chunks).flatten()


def collect_rollouts(
    model: OnPolicyAlgorithm,
    env: VecEnv,
    callback: BaseCallback,
    rollout_buffer: RolloutBuffer,
    n_rollout_steps: int,
) -> bool:
    """SB3's ``OnPolicyAlgorithm.collect_rollouts``, the actor alone acting, the critic evaluated after the rollout.

    Each step asks the policy for its action distribution only (``get_distribution``: actions, log-probabilities,
    SB3's draws and checks); the values of the whole rollout, of the truncated episodes' last observations
    (bootstraps) and of the last observation come from one batched ``predict_values`` pass each.
    """
    assert model._last_obs is not None, "No previous observation was provided"
    policy = model.policy
    policy.set_training_mode(False)
    n_steps = 0
    rollout_buffer.reset()
    if model.use_sde:
        policy.reset_noise(env.num_envs)
    callback.on_rollout_start()
    no_values = th.zeros(env.num_envs)
    truncated: list[tuple[int, int, np.ndarray | dict]] = []  # (buffer position, env index, terminal observation)
    while n_steps < n_rollout_steps:
        if model.use_sde and model.sde_sample_freq > 0 and n_steps % model.sde_sample_freq == 0:
            policy.reset_noise(env.num_envs)
        with th.no_grad():
            obs_tensor = obs_as_tensor(model._last_obs, model.device)  # type: ignore[arg-type]
            distribution = policy.get_distribution(obs_tensor)
            actions = distribution.get_actions()
            log_probs = distribution.log_prob(actions)
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
        rollout_buffer.add(model._last_obs, actions, rewards, model._last_episode_starts, no_values, log_probs)  # type: ignore[arg-type]
        model._last_obs = new_obs  # type: ignore[assignment]
        model._last_episode_starts = dones

    values = predict_values(policy, flat_observations(rollout_buffer, model.device, env_major=False))
    rollout_buffer.values[:] = values.cpu().numpy().reshape(rollout_buffer.values.shape)
    if truncated:  # bootstrap the truncated episodes with the value of their last observation (SB3 #633)
        terminal_values = predict_values(policy, obs_as_tensor(_stack([obs for *_, obs in truncated]), model.device))
        for (pos, idx, _), value in zip(truncated, terminal_values.cpu().numpy()):
            rollout_buffer.rewards[pos, idx] += model.gamma * value
    with th.no_grad():
        values = policy.predict_values(obs_as_tensor(new_obs, model.device))  # type: ignore[arg-type]
    rollout_buffer.compute_returns_and_advantage(last_values=values, dones=dones)
    callback.update_locals(locals())
    callback.on_rollout_end()
    return True


def train_ppo(model, clip_params: list[th.nn.Parameter] | None = None) -> None:
    """One PPO update: SB3's ``PPO.train`` after ``set_training_mode``/learning rate, with the same logs.

    The rollout is turned into tensors once per update (SB3 copies every minibatch out of numpy), losses are logged
    without a conversion per minibatch, and gradients are clipped by ``clip_grad_norm_`` with ``foreach=True``
    (SB3 clips tensor by tensor on a CPU; the encoder adds many tensors).

    :param clip_params: Parameters whose gradient norm is clipped (default: all of the policy's)
    """
    policy, buffer = model.policy, model.rollout_buffer
    clip_range = model.clip_range(model._current_progress_remaining)
    clip_range_vf = None if model.clip_range_vf is None else model.clip_range_vf(model._current_progress_remaining)
    params = list(policy.parameters()) if clip_params is None else clip_params
    n, device = buffer.buffer_size * buffer.n_envs, model.device

    def flat(array: np.ndarray) -> th.Tensor:  # SB3's training order (env-major), as RolloutBuffer.get
        return th.as_tensor(RolloutBuffer.swap_and_flatten(array), device=device)

    observations = flat_observations(buffer, device, env_major=True)
    actions = flat(buffer.actions).float()  # (n, action_dim), as RolloutBuffer._get_samples casts them
    if isinstance(model.action_space, spaces.Discrete):
        actions = actions.long().flatten()
    old_values, old_log_prob = flat(buffer.values).flatten(), flat(buffer.log_probs).flatten()
    all_advantages, returns = flat(buffer.advantages).flatten(), flat(buffer.returns).flatten()

    entropy_losses, pg_losses, value_losses, clip_fractions = [], [], [], []
    continue_training = True
    for epoch in range(model.n_epochs):
        approx_kl_divs = []
        permutation = th.as_tensor(np.random.permutation(n), device=device)  # the draw of RolloutBuffer.get
        for start in range(0, n, model.batch_size):
            index = permutation[start : start + model.batch_size]
            values, log_prob, entropy = policy.evaluate_actions(rows(observations, index), actions[index])
            values = values.flatten()
            advantages = all_advantages[index]
            if model.normalize_advantage and len(advantages) > 1:
                advantages = (advantages - advantages.mean()) / (advantages.std() + 1e-8)
            ratio = th.exp(log_prob - old_log_prob[index])
            policy_loss = -th.min(advantages * ratio, advantages * th.clamp(ratio, 1 - clip_range, 1 + clip_range)).mean()
            if clip_range_vf is None:
                values_pred = values
            else:
                old = old_values[index]
                values_pred = old + th.clamp(values - old, -clip_range_vf, clip_range_vf)
            value_loss = F.mse_loss(returns[index], values_pred)
            entropy_loss = th.mean(log_prob) if entropy is None else -th.mean(entropy)
            loss = policy_loss + model.ent_coef * entropy_loss + model.vf_coef * value_loss
            with th.no_grad():
                log_ratio = log_prob - old_log_prob[index]
                approx_kl_divs.append(th.mean((th.exp(log_ratio) - 1) - log_ratio))
                pg_losses.append(policy_loss.detach())
                clip_fractions.append(th.mean((th.abs(ratio - 1) > clip_range).float()))
                value_losses.append(value_loss.detach())
                entropy_losses.append(entropy_loss.detach())
            if model.target_kl is not None and approx_kl_divs[-1].item() > 1.5 * model.target_kl:
                continue_training = False
                if model.verbose >= 1:
                    print(f"Early stopping at step {epoch} due to reaching max kl: {approx_kl_divs[-1].item():.2f}")
                break
            policy.optimizer.zero_grad()
            loss.backward()
            th.nn.utils.clip_grad_norm_(params, model.max_grad_norm, foreach=True)
            policy.optimizer.step()
        model._n_updates += 1
        if not continue_training:
            break

    def mean(values: list[th.Tensor]) -> float:
        return th.stack(values).mean().item() if values else float("nan")

    logger = model.logger
    logger.record("train/entropy_loss", mean(entropy_losses))
    logger.record("train/policy_gradient_loss", mean(pg_losses))
    logger.record("train/value_loss", mean(value_losses))
    logger.record("train/approx_kl", mean(approx_kl_divs))
    logger.record("train/clip_fraction", mean(clip_fractions))
    logger.record("train/loss", loss.item())
    logger.record("train/explained_variance", explained_variance(buffer.values.flatten(), buffer.returns.flatten()))
    if hasattr(policy, "log_std"):
        logger.record("train/std", th.exp(policy.log_std).mean().item())
    logger.record("train/n_updates", model._n_updates, exclude="tensorboard")
    logger.record("train/clip_range", clip_range)
    if clip_range_vf is not None:
        logger.record("train/clip_range_vf", clip_range_vf)
