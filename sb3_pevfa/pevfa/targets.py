"""Value targets of historical samples: lambda-returns recomputed with the current critic at each sample's policy.

SB3 computes a rollout's TD(lambda) returns once, with the critic of that moment; kept in the history, they stay
the guesses of that old critic. A PeVFA can do better: V(s, chi_k) of the *current* critic for the policy k that
collected the samples bootstraps fresh lambda-returns of that policy (:func:`lambda_returns`, SB3's GAE recursion
over any number of stacked rollouts).
"""

import numpy as np


def lambda_returns(
    rewards: np.ndarray,
    values: np.ndarray,
    episode_starts: np.ndarray,
    last_values: np.ndarray,
    last_episode_starts: np.ndarray,
    gamma: float,
    gae_lambda: float,
) -> np.ndarray:
    """TD(lambda) returns (GAE advantages plus values), as SB3's ``RolloutBuffer.compute_returns_and_advantage``.

    :param rewards: ``(..., n_steps, n_envs)``; ``values`` and ``episode_starts`` alike
    :param last_values: Values of the observations after the last step, ``(..., n_envs)``
    :param last_episode_starts: Whether those observations start new episodes, ``(..., n_envs)``
    """
    advantages = np.zeros_like(values, dtype=np.float32)
    gae = np.zeros_like(last_values, dtype=np.float32)
    n_steps = values.shape[-2]
    for step in reversed(range(n_steps)):
        if step == n_steps - 1:
            not_done, next_values = 1.0 - last_episode_starts, last_values
        else:
            not_done, next_values = 1.0 - episode_starts[..., step + 1, :], values[..., step + 1, :]
        delta = rewards[..., step, :] + gamma * next_values * not_done - values[..., step, :]
        gae = delta + gamma * gae_lambda * not_done * gae
        advantages[..., step, :] = gae
    return advantages + values
