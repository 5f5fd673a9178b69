"""Zero-shot policy values: the PeVFA's value of a policy at given states, from the policy alone (no rollout)."""

import pathlib

import numpy as np
import torch as th
from stable_baselines3 import PPO
from stable_baselines3.common.base_class import BaseAlgorithm
from stable_baselines3.common.policies import ActorCriticPolicy
from stable_baselines3.common.preprocessing import get_action_dim
from stable_baselines3.common.utils import obs_as_tensor

from sb3_pevfa.pevfa.off_policy import OffPolicyPeVFA
from sb3_pevfa.pevfa.records import ActorLayout, PolicyRecord, batch_size, record_policy, rows, state_dim

PolicyLike = ActorCriticPolicy | BaseAlgorithm | str | pathlib.Path | dict | np.ndarray


def _record(model, policy: PolicyLike, observations) -> dict[str, np.ndarray]:
    """The record of ``policy``, as the history stores it."""
    if isinstance(policy, (str, pathlib.Path)):  # PPOPeVFA's, A2CPeVFA's or SB3's PPO's or A2C's: SB3's PPO reads
        policy = PPO.load(policy, device=model.device).policy  # any of their policies (each file names its class)
    if isinstance(policy, BaseAlgorithm):
        policy = policy.policy
    if isinstance(policy, ActorCriticPolicy):
        layout = ActorLayout.from_policy(policy)
        if layout != model.policy.layout:
            raise ValueError(f"The policy's actor {layout} differs from the model's {model.policy.layout}")
        n_pairs = model.policy.n_recorded_pairs
        probe = model.history.sample_observations(n_pairs) if n_pairs else None
        if n_pairs and probe is None:  # empty history: probe at the given observations
            probe = rows(observations, np.resize(np.arange(batch_size(observations)), n_pairs))
        return record_policy(policy, layout, probe, np.zeros(model.policy.code_dim))
    if isinstance(policy, np.ndarray):
        representation = model.policy.representation
        if representation.uses_state_action_pairs or representation.uses_codes:
            raise ValueError(
                f"A bare parameter vector is not enough for representation={model.policy.representation_name!r}: "
                "pass the policy, a saved model or a history record"
            )
        return {
            "params": policy.astype(np.float32),
            "states": np.zeros((0, state_dim(model.observation_space)), np.float32),
            "actions": np.zeros((0, get_action_dim(model.action_space)), np.float32),
            "codes": np.zeros(0, np.float32),
        }
    if isinstance(policy, dict):
        return {key: np.asarray(value, dtype=np.float32) for key, value in policy.items()}
    raise TypeError(
        f"Expected an SB3 policy or model, a saved model path, a record dict or a parameter vector, got {type(policy)}"
    )


def predict_policy_values(model, policy: PolicyLike, observations: np.ndarray | dict[str, np.ndarray]) -> np.ndarray:
    """V(s, chi_policy) of a PPOPeVFA model at ``observations`` (a batch), without running the policy.

    :param policy: An SB3 actor-critic policy or model with the model's actor architecture, the path of a saved
        model, a record of the history (``history.records([i])`` entries for one policy) or, for parameter-based
        representations, a flat parameter vector
    :return: Values, shape ``(batch,)``
    """
    if isinstance(model, OffPolicyPeVFA):
        raise TypeError(f"predict_policy_values reads V(s, chi) of a PPOPeVFA or A2CPeVFA model; {type(model).__name__}'s "
                        "critic is Q(s, a, chi): chi = model.policy.critic.representation(PolicyRecord.from_numpy("
                        "model.history.records([snapshot_id]), model.device)), then model.policy.critic(observations, "
                        "actions, chi) gives the twin critics' values")  # fmt: skip
    record = _record(model, policy, observations)
    if record["params"].ndim == 1:
        record = {key: value[None] for key, value in record.items()}
    training = model.policy.training
    model.policy.set_training_mode(False)
    with th.no_grad():
        embedding = model.policy.embed(PolicyRecord.from_numpy(record, model.device))
        values = model.policy.predict_values(obs_as_tensor(observations, model.device), embedding)
    model.policy.set_training_mode(training)
    return values.flatten().cpu().numpy()
