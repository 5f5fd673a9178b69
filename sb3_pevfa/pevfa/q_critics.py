"""Twin policy-extended critics Q(s, a, chi_pi) for SB3's off-policy algorithms (SAC, TD3).

Each critic is a state-action stream (SB3's ``net_arch["qf"]`` layers on [features, action], by default all but the
last) and the PeVFA head of
the on-policy critic (:class:`~sb3_pevfa.pevfa.critics.PeVFAValueHead`: chi -> embedding stream, concatenated,
head -> 1). The encoder of chi lives in the critic, so that the target critic holds a Polyak copy of it.

Where chi is not given, it is the embedding of the *live* actor: its flat parameters copied without gradient (the
actor is never trained through its own embedding) and, for the ``random`` representation, the code of its latest
snapshot. The encoder learns from the critic's own loss only: where the actions carry a gradient (SAC's actor loss,
TD3's ``q1_forward``), chi is computed without one. The flat copy is taken once per change of the actor's weights
(SB3's target and critic calls of a gradient step read the same one).
"""

import inspect
from typing import Any

import torch as th
from gymnasium import spaces
from stable_baselines3.common.policies import BaseModel
from stable_baselines3.common.preprocessing import get_action_dim
from stable_baselines3.common.torch_layers import BaseFeaturesExtractor, CombinedExtractor, NatureCNN, create_mlp
from stable_baselines3.common.type_aliases import Schedule
from torch import nn
from torch.nn import functional as F

from sb3_pevfa.common.checks import check_argument_names, check_dict, check_layer_sizes, init_parameters, is_int
from sb3_pevfa.common.model_file import sb3_base
from sb3_pevfa.common.training_mode import OnePassTrainingMode
from sb3_pevfa.pevfa.critics import PeVFAValueHead
from sb3_pevfa.pevfa.records import ActorLayout, PolicyRecord, has_image, state_dim
from sb3_pevfa.pevfa.representations import make_representation

#: Representations an off-policy critic can read: the actor's parameters, its actions at replay states, its outputs
#: at learned probe states, a random code per snapshot, or nothing
OFF_POLICY_REPRESENTATIONS = ("opr", "spr", "fingerprint", "random", "none")


class SplitLinear(th.autograd.Function):
    """A linear layer on ``[latent, code[pairing]]`` with its weight's latent and code columns applied apart: the code
    columns once per distinct code (a bias per code). The gradient of the weight is assembled whole, where autograd
    through two slices of it would zero-fill and add a full-size copy per slice."""

    @staticmethod
    def forward(ctx: Any, latent: th.Tensor, code: th.Tensor, weight: th.Tensor, bias: th.Tensor,
                pairing: th.Tensor | None) -> th.Tensor:  # fmt: skip
        """:param latent: ``(batch, width)``; :param code: ``(1, batch or P, weight columns - width)``; :param pairing:
        the row of ``code`` of each input (None: one code for all, or one per input)"""
        width = latent.shape[1]
        per_code = F.linear(code, weight[:, width:], bias)
        ctx.save_for_backward(latent, code, weight, pairing)
        # the per-code bias added by the product itself (one addmm, as nn.Linear's bias)
        return th.addmm(per_code if pairing is None else per_code[pairing], latent, weight[:, :width].t())

    @staticmethod
    def backward(ctx: Any, grad: th.Tensor) -> tuple[th.Tensor | None, ...]:
        latent, code, weight, pairing = ctx.saved_tensors
        width = latent.shape[1]
        if pairing is None:
            per_code = grad.sum(0, keepdim=True) if code.shape[0] == 1 else grad
        else:
            per_code = grad.new_zeros(code.shape[0], grad.shape[1]).index_add_(0, pairing, grad)
        needs = ctx.needs_input_grad
        weight_grad = None
        if needs[2] and th.is_grad_enabled():  # a double backward: differentiable operations
            weight_grad = th.cat([grad.t() @ latent, per_code.t() @ code], dim=1)
        elif needs[2]:  # both blocks written in place into one gradient (no concatenated copy)
            weight_grad = weight.new_empty(weight.shape)
            th.mm(grad.t(), latent, out=weight_grad[:, :width])
            th.mm(per_code.t(), code, out=weight_grad[:, width:])
        return (
            grad @ weight[:, :width] if needs[0] else None,
            per_code @ weight[:, width:] if needs[1] else None,
            weight_grad,
            per_code.sum(0) if needs[3] else None,
            None,
        )


class QStream(nn.Module):
    """One critic: the state-action stream and the PeVFA head."""

    def __init__(self, stream: nn.Module, head: PeVFAValueHead):
        super().__init__()
        self.stream, self.head = stream, head

    def forward(self, inputs: th.Tensor, chi: th.Tensor, pairing: th.Tensor | None = None) -> th.Tensor:
        """:param chi: ``(1 or P, embedding_dim)``; :param pairing: the row of chi of each input (None: one chi for
        all, or one per input)"""
        latent, head = self.stream(inputs), self.head
        if head.embedding_net is None or head.combine != "concat" or not len(head.hidden):
            return head(latent, chi if pairing is None else chi[pairing])
        # the head's first layer on [latent, code] is its latent columns on the batch plus its code columns on each
        # distinct code, a bias per code (the same function, without a batch of copies of the codes)
        first = head.hidden[0]
        code = head.embedding_net(head.chi_norm(chi))
        return head.output(head.hidden[1:](SplitLinear.apply(latent, code, first.weight, first.bias, pairing)))


class PeVFAContinuousCritic(BaseModel):
    """SB3's :class:`~stable_baselines3.common.policies.ContinuousCritic` with chi as an input of every critic.

    :param layout: The actor's parameter layout
    :param actor_holder: A one-element tuple of the policy whose actor is live (its ``actor_parts``, read at each call
        without gradient; a tuple, so that the policy is not a submodule of its own critic)
    :param representation: ``opr``, ``spr``, ``fingerprint``, ``random`` or ``none``
    :param embedding_arch: The embedding stream of chi
    :param head_arch: Layers after the two streams are concatenated; None: the last layer of ``net_arch`` (the critic
        then has SB3's layers, chi entering before the last hidden one)
    """

    def __init__(
        self,
        observation_space: spaces.Space,
        action_space: spaces.Box,
        net_arch: list[int],
        features_extractor: BaseFeaturesExtractor,
        features_dim: int,
        activation_fn: type[nn.Module] = nn.ReLU,
        normalize_images: bool = True,
        n_critics: int = 2,
        share_features_extractor: bool = True,
        *,
        layout: ActorLayout,
        actor_holder: tuple[nn.Module],
        representation: str = "opr",
        embedding_dim: int = 64,
        representation_kwargs: dict[str, Any] | None = None,
        n_state_action_pairs: int = 0,
        embedding_arch: tuple[int, ...] = (64,),
        head_arch: tuple[int, ...] | None = None,
        critic_activation_fn: type[nn.Module] = nn.ReLU,
        chi_normalization: str = "none",
    ):
        super().__init__(
            observation_space, action_space, features_extractor=features_extractor, normalize_images=normalize_images
        )
        if representation not in OFF_POLICY_REPRESENTATIONS:
            valid = OFF_POLICY_REPRESENTATIONS
            raise ValueError(f"Unknown representation {representation!r} of an off-policy PeVFA, valid choices: {valid}")
        action_dim = get_action_dim(self.action_space)
        self.share_features_extractor = share_features_extractor
        self.n_critics = n_critics
        self.layout = layout
        self.actor_holder = actor_holder
        self.q_networks: list[nn.Module] = []
        if head_arch is None:
            net_arch, head_arch = list(net_arch[:-1]), tuple(net_arch[-1:])
        stream_dim = net_arch[-1] if net_arch else features_dim + action_dim
        for idx in range(n_critics):  # SB3's order of layers (and of random draws) where chi is absent
            stream = nn.Sequential(*create_mlp(features_dim + action_dim, -1, list(net_arch), activation_fn))
            head_embedding = 0 if representation == "none" else embedding_dim
            head = PeVFAValueHead(stream_dim, head_embedding, list(embedding_arch), list(head_arch), "concat",
                                  critic_activation_fn, chi_normalization)  # fmt: skip
            q_net = QStream(stream, head)
            self.add_module(f"qf{idx}", q_net)
            self.q_networks.append(q_net)
        self.representation = make_representation(
            representation, layout, observation_space, action_space, embedding_dim, **(representation_kwargs or {})
        )
        #: The live actor's random code (``random``): its latest snapshot's
        codes = th.zeros(embedding_dim if representation == "random" else 0)
        self.register_buffer("behaviour_codes", codes, persistent=codes.numel() > 0)  # saved where used
        #: The states of the live actor's state-action pairs (``spr``): its latest snapshot's
        states = th.zeros(n_state_action_pairs, state_dim(observation_space))
        self.register_buffer("pair_states", states, persistent=states.numel() > 0)
        #: The live actor's chi carries a gradient into the encoder in the critic's loss (else only explicit chi do,
        #: the snapshots' in OffPolicyPeVFA, and the live chi is computed once per change of the actor or encoder)
        self.live_chi_gradient = True
        self._cache: dict[str, tuple[tuple, th.Tensor]] = {}
        #: The live actor's layers and flat copy and the count of its moves (shared with the target critic by
        #: :meth:`share_actor_copy`)
        self._actor_cache: dict[str, Any] = {"generation": 0}
        #: Bumped after each step of the critic's optimizer, as the actor's count after each of its steps (a fused
        #: optimizer moves the weights without their version counters): chi and the actor's flat copy are computed
        #: again only when what they read moved
        self.generation = 0

    @property
    def actor_generation(self) -> int:
        """Steps of the actor's optimizer seen (twice per step where the target shares the count: one hook each)."""
        return self._actor_cache["generation"]

    def touch_actor(self, *_: Any) -> None:
        """Mark the actor's weights as moved (its optimizer's step hook)."""
        self._actor_cache["generation"] += 1

    def touch(self, *_: Any) -> None:
        """Mark the encoder's weights as moved (the critic's optimizer's step hook)."""
        self.generation += 1

    def share_actor_copy(self, other: "PeVFAContinuousCritic") -> None:
        """Read the live actor's flat copy and the count of its moves from ``other``'s cache (the target critic from
        the critic's: one copy per move of the actor, for both)."""
        self._actor_cache = other._actor_cache

    def _cached(self, name: str, key: tuple, compute: Any, cache: dict | None = None) -> Any:
        """``compute()``, again only when ``key`` changed since the last call under ``name`` in ``cache`` (default:
        the critic's own; never kept from inside ``th.inference_mode``: its tensors cannot be used by a later
        update)."""
        if th.is_inference_mode_enabled():
            return compute()
        cache = self._cache if cache is None else cache
        if name not in cache or cache[name][0] != key:
            cache[name] = (key, compute())
        return cache[name][1]

    def _actor_key(self) -> tuple:
        """What the live actor's weights are now: the generation, the storage and version of each tensor."""
        actor = self.actor_holder[0]
        layers = self._cached("layers", (actor.actor,), lambda: self.layout.linear_layers(actor), self._actor_cache)
        return (self.actor_generation, *((t.data_ptr(), t._version) for layer in layers for t in (layer.weight, layer.bias)))

    def _actor_params(self) -> th.Tensor:
        """The live actor's flat parameters ``(1, n_params)``, copied again only when they moved."""
        flatten = lambda: self.layout.flatten(self.actor_holder[0]).to(self.behaviour_codes.device)[None]  # noqa: E731
        return self._cached("params", self._actor_key(), flatten, self._actor_cache)

    def actor_actions(self, states: th.Tensor) -> th.Tensor:
        """The live actor's deterministic actions (SAC: its squashed mean) at its features, without gradient."""
        with th.no_grad():
            return self.actor_holder[0].deterministic_actions(states)

    def actor_record(self) -> PolicyRecord:
        """The live actor's record: its flat parameters (a copy, without gradient), its actions at its latest
        snapshot's states and that snapshot's code."""
        states = self.pair_states
        key = (*self._actor_key(), states.data_ptr(), states._version)
        actions = self._cached("actions", key, lambda: self.actor_actions(states)) if len(states) else None
        empty = self.behaviour_codes.new_zeros(1, 0)
        if actions is None:
            return PolicyRecord(self._actor_params(), empty, empty, self.behaviour_codes[None])
        return PolicyRecord(self._actor_params(), states[None], actions[None], self.behaviour_codes[None])

    def live_embedding(self, grad: bool = True) -> th.Tensor:
        """chi of the live actor, ``(1, embedding_dim)``, with gradient into the encoder where ``grad`` and gradients
        are enabled (else computed once per change of the actor's or the encoder's weights, or of the code)."""
        if self.representation.embedding_dim == 0:
            return self.behaviour_codes.new_zeros(1, 0)
        record = self.actor_record()
        if grad and th.is_grad_enabled():
            return self.representation(record)
        tensors = (self.behaviour_codes, self.pair_states, *self.representation.parameters())
        # the target critic's encoder moves by SB3's Polyak update, which bumps no counter: after the optimizers' steps
        # of the same gradient step (their hooks), before its next call
        key = (*self._actor_key(), self.generation, self.representation.training)
        key += tuple((t.data_ptr(), t._version) for t in tensors)
        with th.no_grad():
            return self._cached("chi", key, lambda: self.representation(record))

    def __getstate__(self) -> dict[str, Any]:
        return {**super().__getstate__(), "_cache": {}, "_actor_cache": {"generation": 0}}  # a copy reads its own actor

    def forward(
        self, obs: th.Tensor, actions: th.Tensor, chi: th.Tensor | None = None, pairing: th.Tensor | None = None
    ) -> tuple[th.Tensor, ...]:
        """Q-values of every critic, ``(batch, 1)`` each.

        :param chi: ``(batch or 1, embedding_dim)``, or ``(P, embedding_dim)`` with ``pairing``; default: the live
            actor's
        :param pairing: The row of chi of each input, ``(batch,)``
        """
        with th.set_grad_enabled(not self.share_features_extractor):
            features = self.extract_features(obs, self.features_extractor)
        chi = self.live_embedding(grad=self.live_chi_gradient and not actions.requires_grad) if chi is None else chi
        inputs = th.cat([features, actions], dim=1)
        return tuple(q_net(inputs, chi, pairing) for q_net in self.q_networks)

    def q1_forward(self, obs: th.Tensor, actions: th.Tensor, chi: th.Tensor | None = None) -> th.Tensor:
        """The first critic's Q-values (TD3's actor loss), the features without gradient as in SB3."""
        with th.no_grad():
            features = self.extract_features(obs, self.features_extractor)
        chi = self.live_embedding(grad=False) if chi is None else chi
        return self.q_networks[0](th.cat([features, actions], dim=1), chi)


class CnnPolicyMixin:
    """SB3's ``CnnPolicy``: a policy whose features extractor is ``NatureCNN`` by default. The CNN is not part of a
    snapshot (the layout records the actor's linear layers)."""

    def __init__(self, *args: Any, features_extractor_class: type[BaseFeaturesExtractor] = NatureCNN, **kwargs: Any):
        super().__init__(*args, features_extractor_class=features_extractor_class, **kwargs)


class MultiInputPolicyMixin:
    """SB3's ``MultiInputPolicy``: a policy for Dict observations, its features extractor ``CombinedExtractor`` by
    default."""

    def __init__(self, *args: Any, features_extractor_class: type[BaseFeaturesExtractor] = CombinedExtractor, **kwargs: Any):
        super().__init__(*args, features_extractor_class=features_extractor_class, **kwargs)


class PeVFAQPolicyMixin(OnePassTrainingMode):
    """What SB3's SAC and TD3 policies need to build :class:`PeVFAContinuousCritic`: the PeVFA keyword arguments,
    ``make_critic`` and the constructor parameters. A policy lists it before its SB3 base and defines
    ``actor_parts()`` (its actor's hidden layers and output heads, as the layout reads them) and
    ``deterministic_actions(features)`` (its actor's deterministic actions at its features: SPR's pairs). The training mode is
    set in one pass over the actor's and the critic's modules (the target critic stays in evaluation mode, as SB3's).

    :param representation: ``opr`` (the actor's parameters), ``spr`` (its actions at replay states), ``fingerprint``
        (its outputs at learned probe states), ``random`` (a code per snapshot) or ``none``
    :param embedding_dim: Size of chi
    :param representation_kwargs: Keyword arguments of the representation
    :param n_state_action_pairs: State-action pairs of each snapshot (``spr`` only)
    :param critic_embedding_arch: The embedding stream of chi
    :param critic_head_arch: Layers after the state-action stream and chi's are concatenated; None (default): the last
        layer of ``net_arch["qf"]``, the stream the layers before it (SB3's critic, chi entering its last hidden layer)
    :param critic_activation_fn: Activation of the embedding stream and the head
    :param chi_normalization: ``"none"`` or ``"layernorm"``
    :param fused_critic_optimizer: Where the critic reads chi, step it with torch's fused Adam (the same update, one
        kernel for all its tensors: its encoder makes the critic 3.5x SAC's count of tensors), unless the optimizer
        is not Adam / AdamW or ``optimizer_kwargs`` chooses ``fused`` or ``foreach``; False: SB3's optimizer as given
    """

    critic_kwargs: dict[str, Any]
    optimizer_kwargs: dict[str, Any]

    def __init__(
        self,
        *args: Any,
        representation: str = "opr",
        embedding_dim: int = 64,
        representation_kwargs: dict[str, Any] | None = None,
        n_state_action_pairs: int = 200,
        critic_embedding_arch: list[int] | tuple[int, ...] = (64,),
        critic_head_arch: list[int] | tuple[int, ...] | None = None,
        critic_activation_fn: type[nn.Module] = nn.ReLU,
        chi_normalization: str = "none",
        fused_critic_optimizer: bool = True,
        **kwargs: Any,
    ):
        # what reaches SB3's policy (a subclass may pass its own): SB3's TypeError would name no valid one
        valid = init_parameters(sb3_base(type(self))) | init_parameters(PeVFAQPolicyMixin)
        check_argument_names(kwargs, valid, f"{type(self).__name__}() (policy_kwargs)")
        if kwargs.get("use_sde"):
            raise ValueError("A PeVFA records actors of linear layers: use_sde=True is not supported")
        if not is_int(n_state_action_pairs) or n_state_action_pairs < 0:
            raise ValueError(f"n_state_action_pairs must be an int >= 0, got {n_state_action_pairs!r}")
        if representation == "spr" and n_state_action_pairs == 0:
            raise ValueError("representation='spr' needs n_state_action_pairs > 0")
        self.representation_name = representation
        self.n_state_action_pairs = int(n_state_action_pairs)
        self.fused_critic_optimizer = bool(fused_critic_optimizer)
        self.pevfa_kwargs = dict(
            representation=representation,
            embedding_dim=embedding_dim,
            representation_kwargs=check_dict("representation_kwargs", representation_kwargs),
            n_state_action_pairs=int(n_state_action_pairs) if representation == "spr" else 0,
            embedding_arch=check_layer_sizes("critic_embedding_arch", critic_embedding_arch),
            head_arch=None if critic_head_arch is None else check_layer_sizes("critic_head_arch", critic_head_arch),
            critic_activation_fn=critic_activation_fn,
            chi_normalization=chi_normalization,
        )
        super().__init__(*args, **kwargs)

    def _build(self, lr_schedule: Schedule) -> None:
        super()._build(lr_schedule)  # type: ignore[misc]
        optimizer = self.critic.optimizer  # type: ignore[attr-defined]
        chosen = {"fused", "foreach", "differentiable"} & set(self.optimizer_kwargs)
        fusable = type(optimizer) in (th.optim.Adam, th.optim.AdamW) and not chosen
        if self.fused_critic_optimizer and self.representation_name != "none" and fusable:
            params = [param for group in optimizer.param_groups for param in group["params"]]
            # its settings as its constructor takes them (AdamW's defaults hold decoupled_weight_decay, not an argument)
            accepted = inspect.signature(type(optimizer)).parameters
            settings = {name: value for name, value in optimizer.defaults.items() if name in accepted}
            self.critic.optimizer = type(optimizer)(params, **{**settings, "foreach": None, "fused": True})  # type: ignore[attr-defined]
        self._link_critics()

    def _link_critics(self) -> None:
        """The target critic reads the critic's flat copy of the actor, and each step of the actor's or the critic's
        optimizer marks both critics' caches of it as stale (once per optimizer: a copied or unpickled optimizer
        comes without its hooks). Where a critic alone is deep-copied, its policy is copied half-way: the critics are
        then left apart (each takes its own copy)."""
        critic, target = self.critic, self.critic_target  # type: ignore[attr-defined]
        if all("_actor_cache" in vars(module) for module in (critic, target)):
            target.share_actor_copy(critic)
        for model, hook in ((self.actor, "touch_actor"), (self.critic, "touch")):  # type: ignore[attr-defined]
            optimizer = getattr(model, "optimizer", None)
            if optimizer is None or getattr(optimizer, "_pevfa_touch_hooks", False):
                continue
            for module in (critic, target):
                optimizer.register_step_post_hook(getattr(module, hook))
            optimizer._pevfa_touch_hooks = True

    def __setstate__(self, state: dict[str, Any]) -> None:
        super().__setstate__(state)  # type: ignore[misc]
        if "critic" in self.__dict__.get("_modules", {}):
            self._link_critics()

    def _mode_roots(self) -> tuple[nn.Module, ...]:
        return (self.actor, self.critic)  # type: ignore[attr-defined]

    def make_critic(self, features_extractor: BaseFeaturesExtractor | None = None) -> PeVFAContinuousCritic:
        critic_kwargs = self._update_features_extractor(self.critic_kwargs, features_extractor)  # type: ignore[attr-defined]
        observation_space = self.observation_space  # type: ignore[attr-defined]
        features_dim, observation_dim = critic_kwargs["features_dim"], state_dim(observation_space)
        mismatched = features_dim != observation_dim and not has_image(observation_space)  # images: SPR's own refusal
        if self.representation_name == "spr" and mismatched:
            raise ValueError(
                f"representation='spr' pairs actions with the flattened observations ({observation_dim} values), which "
                f"the actor's features extractor maps to {features_dim}: use 'opr', 'fingerprint', 'random' or 'none'"
            )
        layout = ActorLayout.from_policy(self)  # type: ignore[arg-type]
        critic = PeVFAContinuousCritic(**critic_kwargs, layout=layout, actor_holder=(self,), **self.pevfa_kwargs)
        return critic.to(self.device)  # type: ignore[attr-defined]

    def _get_constructor_parameters(self) -> dict[str, Any]:
        data = super()._get_constructor_parameters()  # type: ignore[misc]
        kwargs = self.pevfa_kwargs
        data.update(
            representation=kwargs["representation"],
            embedding_dim=kwargs["embedding_dim"],
            representation_kwargs=kwargs["representation_kwargs"],
            n_state_action_pairs=self.n_state_action_pairs,
            critic_embedding_arch=kwargs["embedding_arch"],
            critic_head_arch=kwargs["head_arch"],
            critic_activation_fn=kwargs["critic_activation_fn"],
            chi_normalization=kwargs["chi_normalization"],
            fused_critic_optimizer=self.fused_critic_optimizer,
        )
        return data
