"""Policy representations chi_pi: one interface, chosen by a string (see ``REPRESENTATIONS``)."""

from typing import Any

import numpy as np
import torch as th
from gymnasium import spaces
from stable_baselines3.common.distributions import StateDependentNoiseDistribution
from stable_baselines3.common.torch_layers import create_mlp
from torch import nn

from sb3_pevfa.common.checks import check_keyword_arguments, is_int
from sb3_pevfa.pevfa.records import ActorLayout, PolicyRecord, encode_actions, encoded_action_dim, has_image, state_dim


class PolicyRepresentation(nn.Module):
    """Maps the records of ``P`` policies (:class:`PolicyRecord`) to embeddings of shape ``(P, embedding_dim)``.

    Subclasses say which fields of a record they read (:attr:`fields`).
    """

    #: Reads state-action pairs (SPR)
    uses_state_action_pairs: bool = False
    #: Reads a fixed random code per policy
    uses_codes: bool = False
    #: The state-action pairs of each record it reads (set by the policy; see the AUX objective's ``separate_pairs``)
    pairs: slice = slice(None)

    def __init__(self, embedding_dim: int):
        super().__init__()
        self.embedding_dim = embedding_dim

    @property
    def fields(self) -> tuple[str, ...]:
        """The fields of :class:`PolicyRecord` this representation reads."""
        if self.uses_state_action_pairs:
            return ("states", "actions")
        return ("codes",) if self.uses_codes else ("params",)

    def forward(self, records: PolicyRecord) -> th.Tensor:
        raise NotImplementedError

    def rollout_rows(self, n_observations: int) -> np.ndarray | None:
        """Rows of a complete rollout's ``n_observations`` observations (env-major) that :meth:`observe_rollout` reads;
        None (the default) where it reads none, and the policy then does no work (see ``observe_rollout`` of
        :class:`~sb3_pevfa.pevfa.policies.PeVFAActorCriticPolicy`)."""
        return None

    def observe_rollout(self, features: th.Tensor) -> None:
        """Read the rows of :meth:`rollout_rows` as the actor's inputs, ``(rows, features_dim)``."""


def _mlp(input_dim: int, arch: tuple[int, ...], activation_fn: type[nn.Module]) -> nn.Sequential:
    """Hidden layers with activations, then a linear output of size ``arch[-1]``."""
    return nn.Sequential(*create_mlp(input_dim, arch[-1], list(arch[:-1]), activation_fn))


class OriginPolicyRepresentation(PolicyRepresentation):
    """OPR (paper Sec. 4, App. D.2): a permutation-invariant code of the actor's parameters.

    Each linear layer is the unordered set of its rows ``[W_row | b]``; a per-layer MLP maps every row and the
    mean over rows is the layer code. The layer codes (and a code of the log-std for Gaussian policies) are
    concatenated and projected to ``embedding_dim``.

    :param layout: The actor's parameter layout
    :param embedding_dim: Size of chi
    :param layer_arch: Per-row MLP (the last entry is the layer code size); authors: 32-32-16
    :param log_std_arch: MLP of the log-std vector
    """

    def __init__(
        self,
        layout: ActorLayout,
        embedding_dim: int = 64,
        layer_arch: tuple[int, ...] = (32, 32, 16),
        log_std_arch: tuple[int, ...] = (32, 16),
        activation_fn: type[nn.Module] = nn.ReLU,
    ):
        super().__init__(embedding_dim)
        self.layout = layout
        self.row_encoders = nn.ModuleList(_mlp(inp + 1, tuple(layer_arch), activation_fn) for _, inp in layout.linear_shapes)
        code_dim = layer_arch[-1] * len(layout.linear_shapes)
        self.log_std_encoder = None
        if layout.log_std_numel:
            self.log_std_encoder = _mlp(layout.log_std_numel, tuple(log_std_arch), activation_fn)
            code_dim += log_std_arch[-1]
        self.projection = nn.Linear(code_dim, embedding_dim)

    def layer_codes(self, records: PolicyRecord, row_weights: list[th.Tensor] | None = None) -> th.Tensor:
        """Concatenated layer (and log-std) codes, ``(P, code_dim)``.

        :param row_weights: Optional per-layer ``(P, out)`` 0/1 weights of the rows to keep (augmentation);
            the layer code is then the mean over the kept rows.
        """
        rows, log_std = self.layout.split(records.params)
        codes = []
        for i, (layer_rows, encoder) in enumerate(zip(rows, self.row_encoders)):
            encoded = encoder(layer_rows)
            if row_weights is None:
                codes.append(encoded.mean(dim=1))
            else:
                weights = row_weights[i].unsqueeze(-1)
                codes.append((encoded * weights).sum(dim=1) / weights.sum(dim=1).clamp(min=1.0))
        if self.log_std_encoder is not None:
            codes.append(self.log_std_encoder(log_std))
        return th.cat(codes, dim=1)

    def forward(self, records: PolicyRecord, row_weights: list[th.Tensor] | None = None) -> th.Tensor:
        return self.projection(self.layer_codes(records, row_weights))


class SurfacePolicyRepresentation(PolicyRepresentation):
    """SPR (paper Sec. 4, App. D.2): mean-pooled MLP code of the policy's state-action pairs.

    In training mode a random subset (``subsample``) of the pairs is kept at every call, as the authors do;
    in evaluation mode all pairs are used, so predictions are deterministic.

    :param pair_arch: MLP applied to every concatenated (state, action) pair
    :param subsample: Fraction of the pairs kept at each training-mode call
    """

    uses_state_action_pairs = True

    def __init__(
        self,
        observation_space: spaces.Space,
        action_space: spaces.Space,
        embedding_dim: int = 64,
        pair_arch: tuple[int, ...] = (64, 64),
        subsample: float = 0.8,
        activation_fn: type[nn.Module] = nn.ReLU,
    ):
        super().__init__(embedding_dim)
        if has_image(observation_space):
            raise ValueError("representation='spr' does not support image observations; use 'opr', 'random' or 'none'")
        if not 0.0 < subsample <= 1.0:
            raise ValueError(f"subsample must be in (0, 1], got {subsample}")
        self.action_space = action_space
        self.subsample = subsample
        input_dim = state_dim(observation_space) + encoded_action_dim(action_space)
        self.pair_encoder = nn.Sequential(*create_mlp(input_dim, -1, list(pair_arch), activation_fn))
        self.projection = nn.Linear(pair_arch[-1], embedding_dim)

    def forward(self, records: PolicyRecord, keep: float | None = None) -> th.Tensor:
        """:param keep: Fraction of pairs to keep (default: ``subsample`` in training mode, all in eval mode)."""
        states, actions = records.states[:, self.pairs], records.actions[:, self.pairs]
        pairs = th.cat([states, encode_actions(actions, self.action_space)], dim=-1)
        n_pairs = pairs.shape[1]
        if n_pairs == 0:
            raise ValueError("representation='spr' needs state-action pairs: n_state_action_pairs must be > 0")
        keep = (self.subsample if self.training else 1.0) if keep is None else keep
        n_keep = max(1, round(keep * n_pairs))
        if n_keep < n_pairs:
            index = th.rand(pairs.shape[:2], device=pairs.device).argsort(dim=1)[:, :n_keep]
            pairs = th.gather(pairs, 1, index.unsqueeze(-1).expand(-1, -1, pairs.shape[-1]))
        return self.projection(self.pair_encoder(pairs).mean(dim=1))


#: Action spaces whose distribution parameters ``fingerprint`` reads
FINGERPRINT_ACTION_SPACES = (spaces.Box, spaces.Discrete, spaces.MultiDiscrete, spaces.MultiBinary)


class FingerprintPolicyRepresentation(PolicyRepresentation):
    """Fingerprint: the policy's action distribution at ``n_probes`` learned probe states (Policy Evaluation Networks,
    Harb et al., 2020; Faccio et al., 2022).

    The probe states live in the actor's input space (the features extractor's output: the flattened, preprocessed
    observation of an MLP policy, in VecNormalize's normalised space where there is one) and are parameters trained by
    the value loss. They are zero until set, once, to ``n_probes`` evenly spaced observations of the first complete
    rollout (env-major order, repeated where it holds fewer; no random draw), and are saved with the policy. All the
    recorded actors are evaluated at them in one batched pass over their stacked flat parameters
    (:meth:`ActorLayout.evaluate`); their distribution's parameters at every probe (Box: mean and log-std, gSDE's
    state-dependent one included; Discrete, MultiDiscrete: log-probabilities; MultiBinary: logits) are concatenated
    and mapped by an MLP to chi.

    :param layout: The actor's parameter layout (with its activation)
    :param action_space: The actor's action space
    :param embedding_dim: Size of chi
    :param n_probes: Number of probe states
    :param encoder_arch: Hidden layers of the MLP from the probes' distribution parameters to chi
    :param activation_fn: Activation of that MLP
    """

    def __init__(
        self,
        layout: ActorLayout,
        action_space: spaces.Space,
        embedding_dim: int = 64,
        n_probes: int = 32,
        encoder_arch: tuple[int, ...] = (64,),
        activation_fn: type[nn.Module] = nn.ReLU,
    ):
        super().__init__(embedding_dim)
        if not isinstance(action_space, FINGERPRINT_ACTION_SPACES):
            names = [space.__name__ for space in FINGERPRINT_ACTION_SPACES]
            raise TypeError(f"representation='fingerprint' supports action spaces {names}, got {action_space}")
        if layout.activation_fn is None:
            raise TypeError(
                "representation='fingerprint' evaluates the recorded actors: their policy_net must be [nn.Linear, "
                "activation] pairs (SB3's MlpExtractor)"
            )
        if (
            isinstance(action_space, spaces.Box)
            and not layout.log_std_numel
            and layout.heads == 1
            and layout.mean_activation_fn is None
        ):
            raise ValueError(
                "representation='fingerprint' of a Box action space needs a Gaussian actor with a log-std (or SAC's "
                "two heads, or TD3's deterministic actor)"
            )
        if isinstance(n_probes, bool) or not isinstance(n_probes, (int, np.integer)) or n_probes <= 0:
            raise ValueError(f"n_probes must be a positive int, got {n_probes!r}")
        if any(int(size) <= 0 for size in encoder_arch):
            raise ValueError(f"encoder_arch sizes must be positive, got {encoder_arch}")
        self.layout = layout
        self.action_space = action_space
        self.n_probes = int(n_probes)
        out_dim = layout.linear_shapes[-1][0]
        head_dims = sum(shape[0] for shape in layout.linear_shapes[len(layout.linear_shapes) - layout.heads :])
        self.sde: StateDependentNoiseDistribution | None = None
        if len(layout.log_std_shape) == 2:  # gSDE: a (latent, 1 or action_dim) log-std matrix
            self.sde = StateDependentNoiseDistribution(out_dim, layout.log_std_shape[1] > 1, layout.use_expln)
            self.sde.latent_sde_dim = layout.log_std_shape[0]
        # Box: the mean and the log-std (an on-policy Gaussian's own or SAC's head, its outputs side by side) or
        # TD3's deterministic action alone; the others: the logits of every action
        self.n_features = head_dims + (out_dim if isinstance(action_space, spaces.Box) and layout.log_std_numel else 0)
        self.probes = nn.Parameter(th.zeros(self.n_probes, layout.linear_shapes[0][1]))
        self.register_buffer("probes_set", th.zeros(()))  # 1.0 once set (a float, as the policy's has_behaviour)
        self.encoder = _mlp(self.n_probes * self.n_features, (*encoder_arch, embedding_dim), activation_fn)

    def rollout_rows(self, n_observations: int) -> np.ndarray | None:
        if bool(self.probes_set):
            return None
        return np.arange(self.n_probes) * n_observations // self.n_probes

    def observe_rollout(self, features: th.Tensor) -> None:
        with th.no_grad():
            self.probes.copy_(features.reshape(self.probes.shape))
            self.probes_set.fill_(1.0)

    def distribution_parameters(self, params: th.Tensor) -> th.Tensor:
        """The action distribution's parameters of ``P`` actors at every probe state, ``(P, n_probes, n_features)``."""
        latent, outputs = self.layout.evaluate(params, self.probes)
        if isinstance(self.action_space, spaces.Box) and not self.layout.log_std_numel:
            return outputs  # SAC's mean and log-std heads, TD3's action
        if isinstance(self.action_space, spaces.Box):
            log_std = self.layout.split(params)[1]
            if self.sde is None:
                log_scale = log_std.unsqueeze(1).expand_as(outputs)
            else:  # SB3's gSDE: std = sqrt(latent^2 @ get_std(log_std)^2 + epsilon) at each state
                std = self.sde.get_std(log_std.reshape(-1, *self.layout.log_std_shape))
                log_scale = 0.5 * th.log(th.matmul(latent**2, std**2) + self.sde.epsilon)
            return th.cat([outputs, log_scale], dim=-1)
        if isinstance(self.action_space, spaces.Discrete):
            return outputs.log_softmax(dim=-1)
        if isinstance(self.action_space, spaces.MultiDiscrete):
            sizes = [int(n) for n in self.action_space.nvec]
            return th.cat([part.log_softmax(dim=-1) for part in outputs.split(sizes, dim=-1)], dim=-1)
        return outputs  # MultiBinary: Bernoulli logits

    def forward(self, records: PolicyRecord) -> th.Tensor:
        return self.encoder(self.distribution_parameters(records.params).flatten(start_dim=1))


class RawPolicyRepresentation(PolicyRepresentation):
    """RPR: the flat parameter vector itself (the critic's embedding stream projects it)."""

    def __init__(self, layout: ActorLayout):
        super().__init__(layout.n_params)

    def forward(self, records: PolicyRecord) -> th.Tensor:
        return records.params


class StatisticsPolicyRepresentation(PolicyRepresentation):
    """Gradient-free parameter statistics: mean, std, min, quartiles and max of every W, b and the log-std."""

    n_statistics = 7

    def __init__(self, layout: ActorLayout):
        n_tensors = 2 * len(layout.linear_shapes) + (1 if layout.log_std_numel else 0)
        super().__init__(self.n_statistics * n_tensors)
        self.layout = layout
        self.register_buffer("quantiles", th.tensor([0.0, 0.25, 0.5, 0.75, 1.0]), persistent=False)

    def _statistics(self, values: th.Tensor) -> th.Tensor:
        values = values.flatten(start_dim=1)
        std = values.std(dim=1, keepdim=True) if values.shape[1] > 1 else th.zeros_like(values[:, :1])
        quantiles = th.quantile(values, self.quantiles.to(values.dtype), dim=1).T
        return th.cat([values.mean(dim=1, keepdim=True), std, quantiles], dim=1)

    def forward(self, records: PolicyRecord) -> th.Tensor:
        rows, log_std = self.layout.split(records.params)
        tensors = [part for layer in rows for part in (layer[..., :-1], layer[..., -1])]
        if log_std is not None:
            tensors.append(log_std)
        return th.cat([self._statistics(tensor) for tensor in tensors], dim=1)


class RandomPolicyRepresentation(PolicyRepresentation):
    """Ran PR: a fixed random vector per policy, uniform in [-1, 1], drawn when the policy is recorded."""

    uses_codes = True

    def forward(self, records: PolicyRecord) -> th.Tensor:
        return records.codes


class NoPolicyRepresentation(PolicyRepresentation):
    """No representation: the PeVFA critic degenerates to a conventional V(s) through the same code path."""

    def __init__(self):
        super().__init__(0)

    def forward(self, records: PolicyRecord) -> th.Tensor:
        return records.params.new_zeros((records.params.shape[0], 0))


#: Valid values of ``representation``.
REPRESENTATIONS = ("opr", "spr", "fingerprint", "rpr", "random", "stats", "none")


def make_representation(
    name: str,
    layout: ActorLayout,
    observation_space: spaces.Space,
    action_space: spaces.Space,
    embedding_dim: int = 64,
    **kwargs: Any,
) -> PolicyRepresentation:
    """Build the representation called ``name`` (one of :data:`REPRESENTATIONS`).

    ``embedding_dim`` sets the size of ``opr``, ``spr``, ``fingerprint`` and ``random``; ``rpr`` and ``stats`` have the size of
    their features, ``none`` has size 0. ``kwargs`` go to the representation's constructor.
    """
    if name not in REPRESENTATIONS:
        raise ValueError(f"Unknown representation {name!r}, valid choices: {REPRESENTATIONS}")
    if not is_int(embedding_dim) or embedding_dim <= 0:
        raise ValueError(f"embedding_dim must be a positive int, got {embedding_dim!r}")
    embedding_dim = int(embedding_dim)
    if name in ("rpr", "stats", "none", "random") and kwargs:
        raise ValueError(f"representation={name!r} takes no representation_kwargs, got {sorted(kwargs)}")
    if name == "opr":
        check_keyword_arguments(OriginPolicyRepresentation, kwargs, "representation_kwargs of 'opr'", skip=2)
        return OriginPolicyRepresentation(layout, embedding_dim, **kwargs)
    if name == "spr":
        check_keyword_arguments(SurfacePolicyRepresentation, kwargs, "representation_kwargs of 'spr'", skip=3)
        return SurfacePolicyRepresentation(observation_space, action_space, embedding_dim, **kwargs)
    if name == "fingerprint":
        check_keyword_arguments(FingerprintPolicyRepresentation, kwargs, "representation_kwargs of 'fingerprint'", skip=3)
        return FingerprintPolicyRepresentation(layout, action_space, embedding_dim, **kwargs)
    if name == "rpr":
        return RawPolicyRepresentation(layout)
    if name == "stats":
        return StatisticsPolicyRepresentation(layout)
    if name == "random":
        return RandomPolicyRepresentation(embedding_dim)
    return NoPolicyRepresentation()
