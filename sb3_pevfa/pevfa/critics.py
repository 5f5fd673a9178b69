"""The value head of a PeVFA critic V(s, chi) (paper Fig. 7)."""

import numpy as np
import torch as th
from stable_baselines3.common.torch_layers import create_mlp
from torch import nn

#: Valid values of ``critic_combine``.
CRITIC_COMBINES = ("concat", "product")
#: Valid values of ``chi_normalization``: chi as the representation gives it, or layer-normalised (bounded scale)
CHI_NORMALIZATIONS = ("none", "layernorm")
#: The critic's embedding stream by default: ReLU (the paper's) over a layer-normalised chi (not in the paper)
CRITIC_DEFAULTS = {"critic_activation_fn": nn.ReLU, "chi_normalization": "layernorm"}
#: The stream of models saved before 0.1.0 wrote it into ``policy_kwargs``: the actor's activation over chi as it is
EARLIER_CRITIC = {"critic_activation_fn": None, "chi_normalization": "none"}
#: An embedding-stream unit whose activation has a slope below this at the behaviour chi counts as saturated
SATURATION_SLOPE = 0.1


class PeVFAValueHead(nn.Module):
    """Combines the state stream (SB3's ``latent_vf``) with an embedding stream of chi and outputs V(s, chi).

    Default (paper Fig. 7, with ``net_arch["vf"] = [64]`` as the state stream):
    chi -> Linear(64) act; concat with the state stream -> Linear(128) act -> Linear(1).
    With ``embedding_dim == 0`` (no representation) it is a conventional critic head: state stream -> head -> 1.

    :param latent_dim: Size of the state stream
    :param embedding_dim: Size of chi (0 for none)
    :param embedding_arch: Layers of the embedding stream
    :param head_arch: Layers after the streams are combined
    :param combine: ``"concat"`` or ``"product"`` (element-wise; the embedding stream then ends at ``latent_dim``)
    :param activation_fn: Activation of the embedding stream and the head (paper: ReLU)
    :param chi_normalization: ``"layernorm"`` normalises chi (``nn.LayerNorm``) before the embedding stream, so its
        scale cannot grow into the activations' flat ends; ``"none"`` (paper) reads chi as it is
    """

    def __init__(
        self,
        latent_dim: int,
        embedding_dim: int,
        embedding_arch: list[int],
        head_arch: list[int],
        combine: str = "concat",
        activation_fn: type[nn.Module] = nn.ReLU,
        chi_normalization: str = "none",
    ):
        super().__init__()
        if combine not in CRITIC_COMBINES:
            raise ValueError(f"Unknown critic_combine {combine!r}, valid choices: {CRITIC_COMBINES}")
        if chi_normalization not in CHI_NORMALIZATIONS:
            raise ValueError(f"Unknown chi_normalization {chi_normalization!r}, valid choices: {CHI_NORMALIZATIONS}")
        if chi_normalization == "layernorm" and embedding_dim == 1:
            raise ValueError("chi_normalization='layernorm' of a one-dimensional chi is constant: use 'none'")
        if any(int(size) <= 0 for size in [*embedding_arch, *head_arch]):
            raise ValueError(f"Layer sizes must be positive, got embedding_arch={embedding_arch}, head_arch={head_arch}")
        self.embedding_dim = embedding_dim
        self.combine = combine
        combined_dim = latent_dim
        self.embedding_net: nn.Module | None = None
        use_norm = chi_normalization == "layernorm" and embedding_dim > 0
        self.chi_norm: nn.Module = nn.LayerNorm(embedding_dim) if use_norm else nn.Identity()
        if embedding_dim > 0:
            if combine == "product":
                self.embedding_net = nn.Sequential(*create_mlp(embedding_dim, latent_dim, list(embedding_arch), activation_fn))
            else:
                self.embedding_net = nn.Sequential(*create_mlp(embedding_dim, -1, list(embedding_arch), activation_fn))
                combined_dim += embedding_arch[-1] if embedding_arch else embedding_dim
        self.hidden = nn.Sequential(*create_mlp(combined_dim, -1, list(head_arch), activation_fn))
        self.output = nn.Linear(head_arch[-1] if head_arch else combined_dim, 1)

    def init_weights(self, init_fn) -> None:
        """Orthogonal init as SB3 does: sqrt(2) for hidden layers, 1 for the output."""
        for module in (self.embedding_net, self.hidden):
            if module is not None:
                module.apply(lambda m: init_fn(m, gain=np.sqrt(2)))
        init_fn(self.output, gain=1.0)

    def forward(self, latent_vf: th.Tensor, embedding: th.Tensor) -> th.Tensor:
        """:param embedding: chi, ``(batch, embedding_dim)`` or ``(1, embedding_dim)`` (broadcast)."""
        if self.embedding_net is None:
            return self.output(self.hidden(latent_vf))
        code = self.embedding_net(self.chi_norm(embedding)).expand(latent_vf.shape[0], -1)
        combined = latent_vf * code if self.combine == "product" else th.cat([latent_vf, code], dim=1)
        return self.output(self.hidden(combined))

    @th.no_grad()
    def saturated_fraction(self, embedding: th.Tensor) -> float:
        """Fraction of the embedding stream's hidden units whose activation is flat at ``embedding`` (slope below
        :data:`SATURATION_SLOPE`: ``|tanh| > 0.95``, or a ReLU at zero), where V hardly moves with chi."""
        if self.embedding_net is None:
            return 0.0
        flat, total = 0, 0
        x = self.chi_norm(embedding)
        for module in self.embedding_net:
            if isinstance(module, nn.Linear):
                x = module(x)
                continue
            eps = 1e-3
            slope = (module(x + eps) - module(x - eps)) / (2 * eps)
            flat += int((slope.abs() < SATURATION_SLOPE).sum())
            total += slope.numel()
            x = module(x)
        return flat / max(total, 1)
