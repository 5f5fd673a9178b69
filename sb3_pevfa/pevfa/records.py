"""Policy records: the raw data that describes one policy (actor parameters, state-action pairs, random code).

A *record* is the one name of a historical policy's data, in code (:class:`PolicyRecord`, :func:`record_policy`,
``PolicyHistory.records``), in saved histories (``record/<field>``) and in the docs. Embeddings are never stored:
they are recomputed from records by the current encoder.
"""

from dataclasses import dataclass
from typing import NamedTuple

import numpy as np
import torch as th
from gymnasium import spaces
from stable_baselines3.common.policies import ActorCriticPolicy
from stable_baselines3.common.preprocessing import get_action_dim, is_image_space, preprocess_obs
from stable_baselines3.common.utils import obs_as_tensor
from torch import nn
from torch.nn import functional as F

#: Names of the fields of a policy record, in storage order.
RECORD_FIELDS = ("params", "states", "actions", "codes")


class PolicyRecord(NamedTuple):
    """The records of ``P`` policies as batched torch tensors: the input of a policy representation.

    :param params: Flat actor parameters, shape ``(P, n_params)`` (see :class:`ActorLayout`)
    :param states: Flattened, preprocessed probe states, shape ``(P, n_pairs, state_dim)``
    :param actions: Actions of each policy at its probe states, rollout-buffer layout ``(P, n_pairs, action_dim)``
    :param codes: Fixed random codes (``random`` representation only), shape ``(P, code_dim)``
    """

    params: th.Tensor
    states: th.Tensor
    actions: th.Tensor
    codes: th.Tensor

    @classmethod
    def from_numpy(cls, data: dict[str, np.ndarray], device: th.device | str = "cpu") -> "PolicyRecord":
        return cls(*(th.as_tensor(data[name], device=device) for name in RECORD_FIELDS))


@dataclass(frozen=True)
class ActorLayout:
    """How the actor's parameters are laid out in a flat parameter vector.

    Every linear layer of the actor (``mlp_extractor.policy_net`` then ``action_net``; a policy with an
    ``actor_parts()`` method names its own hidden layers and output heads, e.g. SAC's ``latent_pi`` then ``mu`` and
    ``log_std``) contributes its matrix ``[W | b]`` of shape ``(out, in + 1)``, row-major: each row is one unit (an
    "operation" in the paper's terms). The log standard deviation of Gaussian policies comes last.
    Convolutional feature extractors are not part of the layout: for CNN policies only the MLP head is recorded.

    With the activation after each hidden layer (and gSDE's ``use_expln``), the layout also says how to evaluate the
    actors of flat parameters (:meth:`evaluate`).
    """

    linear_shapes: tuple[tuple[int, int], ...]
    log_std_shape: tuple[int, ...]
    #: The activation after every hidden layer of ``policy_net``; None where the head is not [Linear, activation]*
    activation_fn: type[nn.Module] | None = nn.Tanh
    #: gSDE's ``use_expln`` (how its log-std becomes a standard deviation)
    use_expln: bool = False
    #: The activation of the Gaussian's mean (the policy's ``mean_activation_fn``); None: linear
    mean_activation_fn: type[nn.Module] | None = None
    #: Output layers, all reading the last hidden layer (SAC: the mean and the log-std heads); the last ``heads``
    #: entries of ``linear_shapes``
    heads: int = 1

    @property
    def log_std_numel(self) -> int:
        return int(np.prod(self.log_std_shape)) if self.log_std_shape else 0

    @property
    def n_params(self) -> int:
        return sum(out * (inp + 1) for out, inp in self.linear_shapes) + self.log_std_numel

    @staticmethod
    def actor_parts(policy: nn.Module) -> tuple[nn.Module, list[nn.Module]]:
        """The actor's hidden layers and its output heads: the policy's own ``actor_parts()``, else SB3's on-policy
        ``mlp_extractor.policy_net`` and ``[action_net]``."""
        if hasattr(policy, "actor_parts"):
            return policy.actor_parts()
        return policy.mlp_extractor.policy_net, [policy.action_net]

    @classmethod
    def linear_layers(cls, policy: nn.Module) -> list[nn.Linear]:
        """The actor's linear layers, from input to output (the heads last)."""
        hidden, heads = cls.actor_parts(policy)
        for module in (hidden, *heads):
            for sub in module.modules():
                if len(list(sub.parameters(recurse=False))) > 0 and not isinstance(sub, nn.Linear):
                    raise TypeError(
                        f"PeVFA records actors made of nn.Linear layers, found {type(sub).__name__} in the actor's head"
                    )
        for head in heads:
            if not isinstance(head, nn.Linear):
                raise TypeError(f"PeVFA expects the actor's output layers to be nn.Linear, got {type(head).__name__}")
        return [*(m for m in hidden.modules() if isinstance(m, nn.Linear)), *heads]

    @classmethod
    def activation(cls, policy: nn.Module) -> type[nn.Module] | None:
        """The class of the activation after every hidden linear layer (SB3's MlpExtractor: one per layer,
        ``activation_fn``); None where the hidden layers are not a sequence of [Linear, activation] pairs."""
        hidden, _ = cls.actor_parts(policy)
        steps = [m for m in hidden.modules() if not isinstance(m, nn.Sequential)]
        kinds = {type(m) for m in steps[1::2]}
        if len(steps) % 2 or not all(isinstance(m, nn.Linear) for m in steps[0::2]) or len(kinds) > 1 or nn.Linear in kinds:
            return None
        return kinds.pop() if kinds else getattr(policy, "activation_fn", None)

    @classmethod
    def from_policy(cls, policy: ActorCriticPolicy) -> "ActorLayout":
        shapes = tuple((layer.out_features, layer.in_features) for layer in cls.linear_layers(policy))
        log_std = getattr(policy, "log_std", None)
        return cls(
            linear_shapes=shapes,
            log_std_shape=tuple(log_std.shape) if isinstance(log_std, th.Tensor) else (),
            activation_fn=cls.activation(policy),
            use_expln=bool(getattr(getattr(policy, "action_dist", None), "use_expln", False)),
            mean_activation_fn=getattr(policy, "mean_activation_fn", None),
            heads=len(cls.actor_parts(policy)[1]),
        )

    def flatten(self, policy: ActorCriticPolicy) -> th.Tensor:
        """Flat copy (detached) of the actor's parameters, shape ``(n_params,)``."""
        with th.no_grad():
            parts = [th.cat([layer.weight, layer.bias.unsqueeze(1)], dim=1).flatten() for layer in self.linear_layers(policy)]
            if self.log_std_numel:
                parts.append(policy.log_std.flatten())
            return th.cat(parts).detach().clone()

    def split(self, params: th.Tensor) -> tuple[list[th.Tensor], th.Tensor | None]:
        """Views of batched flat parameters ``(P, n_params)``: per layer ``(P, out, in + 1)``, and log-std ``(P, k)``."""
        rows, offset = [], 0
        for out, inp in self.linear_shapes:
            size = out * (inp + 1)
            rows.append(params[:, offset : offset + size].reshape(-1, out, inp + 1))
            offset += size
        log_std = params[:, offset:] if self.log_std_numel else None
        return rows, log_std

    def evaluate(self, params: th.Tensor, inputs: th.Tensor) -> tuple[th.Tensor, th.Tensor]:
        """The actors of batched flat parameters at ``inputs``, all in one batched pass (no loop over the actors).

        :param params: Flat parameters of ``P`` actors, ``(P, n_params)``
        :param inputs: The actor's inputs (the features extractor's outputs), ``(K, in)`` for all or ``(P, K, in)``
        :return: ``policy_net``'s output (gSDE's latent) ``(P, K, hidden)`` and ``action_net``'s ``(P, K, out)``
            (through ``mean_activation_fn`` where the policy has one); with several heads, theirs side by side
        """
        if self.activation_fn is None:
            raise TypeError("Evaluating actors needs a policy_net of [nn.Linear, activation] pairs (SB3's MlpExtractor)")
        activation = self.activation_fn()
        rows, _ = self.split(params)
        latent = inputs
        for layer in rows[: -self.heads]:
            latent = activation(_batched_linear(latent, layer))
        outputs = th.cat([_batched_linear(latent, head) for head in rows[-self.heads :]], dim=-1)
        if self.mean_activation_fn is not None:
            outputs = self.mean_activation_fn()(outputs)
        return latent.expand(len(params), *latent.shape[-2:]), outputs


def _batched_linear(inputs: th.Tensor, rows: th.Tensor) -> th.Tensor:
    """``inputs @ W.T + b`` for each of ``P`` layers ``rows = [W | b]`` ``(P, out, in + 1)``: ``(P, K, out)``."""
    return th.matmul(inputs, rows[..., :-1].transpose(1, 2)) + rows[:, None, :, -1]


def batch_size(obs: np.ndarray | th.Tensor | dict) -> int:
    """Number of observations in a batch (an array or tensor, or a dict of them)."""
    return len(next(iter(obs.values())) if isinstance(obs, dict) else obs)


def rows(obs: np.ndarray | th.Tensor | dict, index: int | slice | np.ndarray | th.Tensor) -> np.ndarray | th.Tensor | dict:
    """The rows ``index`` of a batch of observations (an array or tensor, or a dict of them)."""
    return {key: value[index] for key, value in obs.items()} if isinstance(obs, dict) else obs[index]


def stack_observations(observations: list) -> np.ndarray | dict[str, np.ndarray]:
    """A list of observation batches (arrays, or dicts of them) stacked along a new first axis."""
    if isinstance(observations[0], dict):
        return {key: np.stack([obs[key] for obs in observations]) for key in observations[0]}
    return np.stack(observations)


def state_dim(observation_space: spaces.Space) -> int:
    """Size of a flattened, preprocessed observation (one-hot for discrete spaces)."""
    return int(spaces.utils.flatdim(observation_space))


def has_image(observation_space: spaces.Space) -> bool:
    if isinstance(observation_space, spaces.Dict):
        return any(is_image_space(space) for space in observation_space.spaces.values())
    return is_image_space(observation_space)


def flatten_observations(obs: th.Tensor | dict[str, th.Tensor], observation_space: spaces.Space) -> th.Tensor:
    """Preprocess (as the policy does) and flatten a batch of observations to ``(batch, state_dim)``."""
    processed = preprocess_obs(obs, observation_space, normalize_images=True)
    if isinstance(processed, dict):
        return th.cat([processed[key].flatten(start_dim=1) for key in observation_space.spaces], dim=1)
    return processed.flatten(start_dim=1)


def flat_states(obs: np.ndarray | dict[str, np.ndarray], observation_space: spaces.Space) -> np.ndarray:
    """:func:`flatten_observations` of a numpy batch, as float32 numpy (SPR's probe states)."""
    with th.no_grad():
        return flatten_observations(obs_as_tensor(obs, th.device("cpu")), observation_space).numpy().astype(np.float32)


def encode_actions(actions: th.Tensor, action_space: spaces.Space) -> th.Tensor:
    """Actions in rollout-buffer layout ``(..., action_dim)`` to network inputs (one-hot for discrete spaces)."""
    if isinstance(action_space, spaces.Discrete):
        return F.one_hot(actions[..., 0].long(), int(action_space.n)).float()
    if isinstance(action_space, spaces.MultiDiscrete):
        return th.cat([F.one_hot(actions[..., i].long(), int(n)).float() for i, n in enumerate(action_space.nvec)], dim=-1)
    return actions.float()


def encoded_action_dim(action_space: spaces.Space) -> int:
    if isinstance(action_space, spaces.Discrete):
        return int(action_space.n)
    if isinstance(action_space, spaces.MultiDiscrete):
        return int(np.sum(action_space.nvec))
    return get_action_dim(action_space)


def record_policy(
    policy: ActorCriticPolicy,
    layout: ActorLayout,
    probe_obs: np.ndarray | dict[str, np.ndarray] | None,
    code: np.ndarray,
) -> dict[str, np.ndarray]:
    """The record of one policy (numpy arrays): flat parameters, and actions sampled at ``probe_obs`` (SPR's pairs).

    With gSDE every probe state gets its own exploration noise, drawn from the policy's current log-std
    (``reset_noise`` over the probe batch; the rollout draws its own afterwards, as SB3 does at every rollout start),
    so the pairs show the policy's exploration rather than one noise draw.

    :param probe_obs: A batch of raw observations (as stored in a rollout buffer), or None for no pairs
    :param code: The policy's random code (empty unless the ``random`` representation is used)
    """
    observation_space, action_space = policy.observation_space, policy.action_space
    params = layout.flatten(policy).cpu().numpy().astype(np.float32)
    if probe_obs is None:
        states = np.zeros((0, state_dim(observation_space)), dtype=np.float32)
        actions = np.zeros((0, get_action_dim(action_space)), dtype=np.float32)
    else:
        with th.no_grad():
            obs_tensor = obs_as_tensor(probe_obs, policy.device)
            if policy.use_sde:
                policy.reset_noise(batch_size(obs_tensor))
            sampled = policy.get_distribution(obs_tensor).get_actions(deterministic=False)
            states = flatten_observations(obs_tensor, observation_space).cpu().numpy().astype(np.float32)
        actions = sampled.reshape(len(states), -1).cpu().numpy().astype(np.float32)
    return {"params": params, "states": states, "actions": actions, "codes": np.asarray(code, dtype=np.float32)}
