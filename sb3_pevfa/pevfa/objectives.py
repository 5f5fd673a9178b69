"""Representation objectives besides the value loss (paper Sec. 4, App. D.3-D.4): contrastive (CL) and auxiliary
action prediction (AUX). Each owns its modules; the policy owns their optimizers (shared encoder + own modules)."""

import copy
from typing import Any

import torch as th
from gymnasium import spaces
from stable_baselines3.common.distributions import make_proba_distribution
from stable_baselines3.common.torch_layers import create_mlp
from stable_baselines3.common.utils import polyak_update
from torch import nn
from torch.nn import functional as F

from sb3_pevfa.common.checks import check_keyword_arguments
from sb3_pevfa.pevfa.records import PolicyRecord, state_dim
from sb3_pevfa.pevfa.representations import (
    OriginPolicyRepresentation,
    PolicyRepresentation,
    SurfacePolicyRepresentation,
)

#: Valid entries of ``representation_objectives``.
OBJECTIVES = ("cl", "aux")
#: The order of their steps in an iteration, Algorithm 3's (AUX steps, then CL steps), whatever order they are named in
TRAINING_ORDER = ("aux", "cl")
#: The paper's environment steps per objective step (App. F.1)
PAPER_TRAIN_FREQ = 10


def training_rank(name: str) -> int:
    """Position of objective ``name`` in an iteration's steps: :data:`TRAINING_ORDER`, an objective not in it last."""
    return TRAINING_ORDER.index(name) if name in TRAINING_ORDER else len(TRAINING_ORDER)


class RepresentationObjective(nn.Module):
    """An extra loss on the encoder, trained every ``train_freq`` environment steps after ``learning_starts`` steps
    on ``batch_policies`` policies drawn from the history, by its own optimizer (``learning_rate``). ``train_freq``
    None: on the cadence of the algorithm's historical critic updates (``history_train_freq``; the paper's 10 where
    they are off)."""

    name: str

    def __init__(self, train_freq: int | None, learning_starts: int, batch_policies: int, learning_rate: float):
        super().__init__()
        for key, value, minimum in (
            ("train_freq", train_freq, 1),
            ("learning_starts", learning_starts, 0),
            ("batch_policies", batch_policies, 2),  # a contrast needs negatives; AUX trains on a batch of policies
        ):
            if key == "train_freq" and value is None:
                continue
            if not isinstance(value, int) or value < minimum:
                raise ValueError(f"{self.name} {key} must be an int >= {minimum}, got {value!r}")
        if not learning_rate > 0:
            raise ValueError(f"{self.name} learning_rate must be positive, got {learning_rate!r}")
        self.train_freq = train_freq
        self.learning_starts = learning_starts
        self.batch_policies = batch_policies
        self.learning_rate = learning_rate

    def loss(self, representation: PolicyRepresentation, records: PolicyRecord) -> tuple[th.Tensor, dict[str, float]]:
        """The loss on a batch of policies, and metrics to log."""
        raise NotImplementedError

    def after_step(self, representation: PolicyRepresentation) -> None:
        """Called after each optimizer step."""


class ContrastiveObjective(RepresentationObjective):
    """InfoNCE with a momentum (EMA) key encoder and a learned bilinear similarity W (CURL-style).

    Query: the online encoder on one augmentation of each policy's record; key: the momentum encoder on another;
    the other policies of the batch are the negatives. Augmentations: OPR drops a random ``mask_ratio`` of the
    hidden units (whole rows, before the mean; the output layer and log-std are kept) and optionally corrupts a
    random ``noise_ratio`` of the parameters with Gaussian noise (``noise_std``); SPR keeps a random
    ``sample_ratio`` of the state-action pairs.

    :param train_freq: Environment steps per step of this objective; None (default): those of the historical critic
        updates (``history_train_freq``: PPOPeVFA 40, A2CPeVFA 200, ``PAPER_SCHEDULE`` the paper's 10), 10 where
        they are off
    :param momentum: EMA rate of the key encoder (paper: 0.01)
    """

    name = "cl"

    def __init__(
        self,
        representation: PolicyRepresentation,
        train_freq: int | None = None,
        learning_starts: int = 5_000,
        batch_policies: int = 32,
        learning_rate: float | None = None,
        momentum: float = 0.01,
        mask_ratio: float = 0.1,
        noise_ratio: float = 0.0,
        noise_std: float = 0.1,
        sample_ratio: float = 0.8,
    ):
        if learning_rate is None:  # paper: 1e-3 for OPR, 5e-4 for SPR
            learning_rate = 5e-4 if isinstance(representation, SurfacePolicyRepresentation) else 1e-3
        super().__init__(train_freq, learning_starts, batch_policies, learning_rate)
        for key, value in (("momentum", momentum), ("mask_ratio", mask_ratio), ("noise_ratio", noise_ratio)):
            if not 0.0 <= value <= 1.0:
                raise ValueError(f"cl {key} must be in [0, 1], got {value}")
        if not 0.0 < sample_ratio <= 1.0:
            raise ValueError(f"cl sample_ratio must be in (0, 1], got {sample_ratio}")
        self.momentum = momentum
        self.mask_ratio = mask_ratio
        self.noise_ratio = noise_ratio
        self.noise_std = noise_std
        self.sample_ratio = sample_ratio
        self.key_encoder = copy.deepcopy(representation)
        self.key_encoder.requires_grad_(False)
        self.bilinear = nn.Parameter(th.eye(representation.embedding_dim))

    def _encode(self, encoder: PolicyRepresentation, records: PolicyRecord) -> th.Tensor:
        """One random augmentation of every policy of the batch, encoded."""
        if isinstance(encoder, OriginPolicyRepresentation):
            params = records.params
            if self.noise_ratio > 0:
                corrupt = th.rand_like(params) < self.noise_ratio
                params = params + corrupt * self.noise_std * th.randn_like(params)
            n_policies = params.shape[0]
            hidden = encoder.layout.linear_shapes[:-1]
            row_weights = [(th.rand(n_policies, out, device=params.device) >= self.mask_ratio).float() for out, _ in hidden]
            row_weights.append(th.ones(n_policies, encoder.layout.linear_shapes[-1][0], device=params.device))
            return encoder(records._replace(params=params), row_weights=row_weights)
        return encoder(records, keep=self.sample_ratio)  # SPR

    def loss(self, representation: PolicyRepresentation, records: PolicyRecord) -> tuple[th.Tensor, dict[str, float]]:
        query = self._encode(representation, records)
        with th.no_grad():
            key = self._encode(self.key_encoder, records)
        logits = query @ self.bilinear @ key.T
        logits = logits - logits.max(dim=1, keepdim=True).values.detach()
        labels = th.arange(len(logits), device=logits.device)
        loss = F.cross_entropy(logits, labels)
        accuracy = (logits.argmax(dim=1) == labels).float().mean().item()
        return loss, {"cl_loss": loss.item(), "cl_accuracy": accuracy}

    def after_step(self, representation: PolicyRepresentation) -> None:
        polyak_update(representation.parameters(), self.key_encoder.parameters(), self.momentum)


class ActionPredictionObjective(RepresentationObjective):
    """AUX: a decoder pi_bar(a | s, chi) trained by negative log-likelihood on each policy's stored state-action pairs.

    The decoder is an MLP (``net_arch``, paper 128-128 ReLU) on [state, chi] followed by SB3's distribution head for
    the action space: diagonal Gaussian (Box), categorical (Discrete), multi-categorical (MultiDiscrete), Bernoulli
    (MultiBinary).

    :param pairs_per_policy: State-action pairs per policy in a batch (paper: 16 policies x 16 pairs)
    :param separate_pairs: With SPR, decode pairs of their own (the paper: records then hold twice the pairs, SPR
        reads the first half, AUX the second), so AUX predicts behaviour rather than reconstruct what chi encodes;
        False decodes the pairs SPR reads
    """

    name = "aux"
    #: The pairs of each record this objective decodes (set by the policy that builds it)
    pairs: slice = slice(None)

    def __init__(
        self,
        representation: PolicyRepresentation,
        observation_space: spaces.Space,
        action_space: spaces.Space,
        train_freq: int | None = 10,
        learning_starts: int = 5_000,
        batch_policies: int = 16,
        learning_rate: float = 1e-3,
        pairs_per_policy: int = 16,
        net_arch: tuple[int, ...] = (128, 128),
        separate_pairs: bool = True,
    ):
        super().__init__(train_freq, learning_starts, batch_policies, learning_rate)
        self.separate_pairs = bool(separate_pairs)
        if not isinstance(pairs_per_policy, int) or pairs_per_policy < 1:
            raise ValueError(f"aux pairs_per_policy must be a positive int, got {pairs_per_policy!r}")
        self.pairs_per_policy = pairs_per_policy
        self.action_space = action_space
        input_dim = state_dim(observation_space) + representation.embedding_dim
        self.decoder = nn.Sequential(*create_mlp(input_dim, -1, list(net_arch), nn.ReLU))
        self.action_dist = make_proba_distribution(action_space)
        head = self.action_dist.proba_distribution_net(net_arch[-1])
        self.action_net, self.log_std = head if isinstance(head, tuple) else (head, None)

    def negative_log_likelihood(self, embeddings: th.Tensor, states: th.Tensor, actions: th.Tensor) -> th.Tensor:
        """Mean NLL of ``actions (P, n, a)`` at ``states (P, n, s)`` under pi_bar(. | s, chi) with chi ``(P, e)``."""
        n_pairs = states.shape[1]
        inputs = th.cat([states, embeddings.unsqueeze(1).expand(-1, n_pairs, -1)], dim=-1).flatten(0, 1)
        params = self.action_net(self.decoder(inputs))
        actions = actions.flatten(0, 1)
        if isinstance(self.action_space, spaces.Discrete):
            actions = actions[:, 0].long()
        if self.log_std is not None:
            distribution = self.action_dist.proba_distribution(params, self.log_std)
        else:
            distribution = self.action_dist.proba_distribution(action_logits=params)
        return -distribution.log_prob(actions).mean()

    def loss(self, representation: PolicyRepresentation, records: PolicyRecord) -> tuple[th.Tensor, dict[str, float]]:
        states, actions = records.states[:, self.pairs], records.actions[:, self.pairs]
        n_policies, n_pairs = states.shape[:2]
        if n_pairs == 0:
            raise ValueError("objective 'aux' needs state-action pairs: n_state_action_pairs must be > 0")
        index = th.randint(n_pairs, (n_policies, self.pairs_per_policy), device=states.device)
        states = th.gather(states, 1, index.unsqueeze(-1).expand(-1, -1, states.shape[-1]))
        actions = th.gather(actions, 1, index.unsqueeze(-1).expand(-1, -1, actions.shape[-1]))
        loss = self.negative_log_likelihood(representation(records), states, actions)
        return loss, {"aux_nll": loss.item()}


def make_objective(
    name: str,
    representation: PolicyRepresentation,
    observation_space: spaces.Space,
    action_space: spaces.Space,
    **kwargs: Any,
) -> RepresentationObjective:
    """Build objective ``name`` (one of :data:`OBJECTIVES`) for a learned representation (``opr`` or ``spr``)."""
    if name not in OBJECTIVES:
        raise ValueError(f"Unknown representation objective {name!r}, valid choices: {OBJECTIVES}")
    if not isinstance(representation, (OriginPolicyRepresentation, SurfacePolicyRepresentation)):
        raise ValueError(
            f"Objective {name!r} trains a learned policy encoder: it needs representation 'opr' or 'spr', "
            f"not a {type(representation).__name__}"
        )
    if name == "cl":
        check_keyword_arguments(ContrastiveObjective, kwargs, "objective_kwargs of 'cl'", skip=1)
        return ContrastiveObjective(representation, **kwargs)
    check_keyword_arguments(ActionPredictionObjective, kwargs, "objective_kwargs of 'aux'", skip=3)
    return ActionPredictionObjective(representation, observation_space, action_space, **kwargs)
