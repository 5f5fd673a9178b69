"""Actor-critic policies whose critic is a PeVFA V(s, chi_pi)."""

import copy
import inspect
from collections.abc import Iterator
from contextlib import contextmanager
from typing import Any

import numpy as np
import torch as th
from gymnasium import spaces
from stable_baselines3.common.buffers import RolloutBuffer
from stable_baselines3.common.policies import ActorCriticPolicy
from stable_baselines3.common.preprocessing import get_action_dim
from stable_baselines3.common.torch_layers import CombinedExtractor, NatureCNN
from stable_baselines3.common.type_aliases import PyTorchObs, Schedule
from stable_baselines3.common.utils import obs_as_tensor
from torch import nn

from sb3_pevfa.common.checks import check_dict, check_layer_sizes, is_int
from sb3_pevfa.common.training_mode import OnePassTrainingMode
from sb3_pevfa.pevfa.critics import CRITIC_DEFAULTS, PeVFAValueHead
from sb3_pevfa.pevfa.objectives import OBJECTIVES, make_objective
from sb3_pevfa.pevfa.records import ActorLayout, PolicyRecord, has_image, rows, state_dim
from sb3_pevfa.pevfa.representations import PolicyRepresentation, make_representation

#: Valid values of ``weight_init`` (None: PyTorch's default, or SB3's orthogonal one with ``ortho_init``)
WEIGHT_INITS = (None, "normal_fan_in")


def _check_objectives(objectives: tuple[str, ...], objective_kwargs: dict[str, dict[str, Any]]) -> None:
    if not isinstance(objective_kwargs, dict) or not all(isinstance(v, dict) for v in objective_kwargs.values()):
        raise TypeError(f"objective_kwargs must map objective names to dicts of settings, got {objective_kwargs!r}")
    unknown = [name for name in objectives if name not in OBJECTIVES]
    if unknown:
        raise ValueError(f"Unknown representation objectives {unknown}, valid choices: {OBJECTIVES}")
    if len(set(objectives)) != len(objectives):
        raise ValueError(f"representation_objectives lists an objective twice: {objectives}")
    unused = sorted(set(objective_kwargs) - set(objectives))
    if unused:
        raise ValueError(f"objective_kwargs given for {unused}, which are not in representation_objectives={objectives}")


def _check_aux(observation_space: spaces.Space, n_state_action_pairs: int) -> None:
    if has_image(observation_space):
        raise ValueError(
            "objective 'aux' predicts actions from state-action pairs, which image observations do not record: "
            "use objective 'cl', or none"
        )
    if n_state_action_pairs == 0:
        raise ValueError("objective 'aux' needs state-action pairs: n_state_action_pairs must be > 0")


def init_normal_fan_in(model: nn.Module) -> None:
    """Every linear layer of ``model``: weights N(0, 1 / fan_in), biases 0 (``weight_init="normal_fan_in"``)."""
    for module in model.modules():
        if isinstance(module, nn.Linear):
            nn.init.normal_(module.weight, std=module.in_features**-0.5)
            nn.init.zeros_(module.bias)


def _check_actor_options(
    action_space: spaces.Space,
    mean_activation_fn: type[nn.Module] | None,
    weight_init: str | None,
    log_std_lr_scale: float,
    kwargs: dict[str, Any],
) -> None:
    if weight_init not in WEIGHT_INITS:
        raise ValueError(f"Unknown weight_init {weight_init!r}, valid choices: {WEIGHT_INITS}")
    if weight_init is not None and kwargs.get("ortho_init", True):
        raise ValueError(f"weight_init={weight_init!r} replaces SB3's orthogonal initialization: pass ortho_init=False")
    if not isinstance(log_std_lr_scale, (int, float)) or not np.isfinite(log_std_lr_scale) or log_std_lr_scale <= 0:
        raise ValueError(f"log_std_lr_scale must be a positive finite float, got {log_std_lr_scale!r}")
    if mean_activation_fn is not None and not (isinstance(action_space, spaces.Box) and not kwargs.get("use_sde")):
        raise ValueError("mean_activation_fn needs a Box action space without gSDE (a Gaussian's mean to squash)")


class PeVFAActorCriticPolicy(OnePassTrainingMode, ActorCriticPolicy):
    """SB3's :class:`~stable_baselines3.common.policies.ActorCriticPolicy` with a policy-extended critic.

    The actor is SB3's, unchanged. The critic V(s, chi) reads the state stream (``net_arch["vf"]``, paper: one layer
    of 64) and chi, a policy's embedding: :meth:`predict_values`, :meth:`evaluate_actions` and :meth:`forward` take
    ``chi`` as an argument. Left out (``chi=None``, as SB3's own loops call them), it is the embedding of the
    *behaviour* policy, the record set by :meth:`set_behaviour_record` (the policy that collected the current data;
    its record, not the live actor, so no gradient reaches the actor through chi). Before any policy is recorded,
    chi is computed from the live actor's parameters.

    Extra parameters (the rest are SB3's):

    :param representation: One of ``opr``, ``spr``, ``fingerprint``, ``rpr``, ``random``, ``stats``, ``none``
    :param embedding_dim: Size of chi for ``opr``, ``spr``, ``fingerprint`` and ``random``
    :param representation_kwargs: Keyword arguments of the representation (e.g. ``layer_arch``, ``subsample``,
        ``n_probes``)
    :param n_state_action_pairs: State-action pairs recorded per policy, where something reads them (SPR, the AUX
        objective); other configurations record none (:attr:`n_recorded_pairs` is 0)
    :param critic_embedding_arch: Embedding stream of the critic (paper: [64])
    :param critic_head_arch: Layers after the streams are combined (paper: [128])
    :param critic_combine: ``concat`` (paper) or ``product``
    :param critic_activation_fn: Activation of the embedding stream and head: ReLU (the paper's, default), any
        activation class, or None for the actor's ``activation_fn`` (SB3's Tanh; the default before 0.1.0's
        ablation, which saturates)
    :param chi_normalization: ``"layernorm"`` (default, not in the paper): chi normalised before the embedding
        stream; ``"none"`` (the paper's) reads chi as the representation gives it
    :param representation_objectives: Extra encoder objectives besides the value loss: any of ``cl``, ``aux``
    :param objective_kwargs: Settings per objective, e.g. ``{"cl": {"batch_policies": 16}}``
        (see :mod:`sb3_pevfa.pevfa.objectives`)
    :param mean_activation_fn: Activation of the Gaussian's mean (e.g. ``nn.Tanh``: the authors' code); None: linear
        (SB3's). Box action spaces without gSDE
    :param weight_init: ``"normal_fan_in"``: every linear layer of the actor, the critic and the encoder N(0, 1/fan_in),
        biases 0 (the authors' code; the objectives' own heads keep PyTorch's); None: PyTorch's, or SB3's orthogonal
        one (``ortho_init``)
    :param log_std_lr_scale: The log-std's learning rate over the actor's (its own parameter group). The authors'
        log-variance, a sum of 13 trainable rows - 1, moves under Adam as one log-std at 6.5x the rate
        (``tests/test_authors_protocol.py`` shows the equivalence)

    Without ``optimizer_kwargs``, Adam runs SB3's settings (``eps=1e-5``) with ``fused=True``; other torch optimizers
    that take ``foreach`` (A2C's RMSprop) get ``foreach=True`` unless ``foreach`` or ``fused`` is given.
    """

    def __init__(
        self,
        observation_space: spaces.Space,
        action_space: spaces.Space,
        lr_schedule: Schedule,
        net_arch: list[int] | dict[str, list[int]] | None = None,
        activation_fn: type[nn.Module] = nn.Tanh,
        *args: Any,
        representation: str = "opr",
        embedding_dim: int = 64,
        representation_kwargs: dict[str, Any] | None = None,
        n_state_action_pairs: int = 200,
        critic_embedding_arch: list[int] | tuple[int, ...] = (64,),
        critic_head_arch: list[int] | tuple[int, ...] = (128,),
        critic_combine: str = "concat",
        critic_activation_fn: type[nn.Module] | None = CRITIC_DEFAULTS["critic_activation_fn"],
        chi_normalization: str = CRITIC_DEFAULTS["chi_normalization"],
        representation_objectives: tuple[str, ...] | list[str] = (),
        objective_kwargs: dict[str, dict[str, Any]] | None = None,
        mean_activation_fn: type[nn.Module] | None = None,
        weight_init: str | None = None,
        log_std_lr_scale: float = 1.0,
        **kwargs: Any,
    ):
        _check_actor_options(action_space, mean_activation_fn, weight_init, log_std_lr_scale, kwargs)
        self.mean_activation_fn = mean_activation_fn
        self.weight_init = weight_init
        self.log_std_lr_scale = float(log_std_lr_scale)
        optimizer_class = kwargs.get("optimizer_class", th.optim.Adam)
        if kwargs.get("optimizer_kwargs") is None and optimizer_class is th.optim.Adam:
            # SB3's Adam settings (eps=1e-5) with the fused kernel: one call per step instead of a Python loop over
            # the parameter tensors (the encoder adds many). Pass optimizer_kwargs=dict(eps=1e-5) for SB3's own.
            kwargs["optimizer_kwargs"] = dict(eps=1e-5, fused=True)
        elif (
            optimizer_class is not th.optim.Adam
            and "foreach" in inspect.signature(optimizer_class).parameters
            and not {"foreach", "fused"} & set(kwargs.get("optimizer_kwargs") or {})
        ):
            # e.g. A2C's RMSprop: torch's multi-tensor kernels (the same update), not a loop over the tensors on a CPU
            kwargs["optimizer_kwargs"] = {**(kwargs.get("optimizer_kwargs") or {}), "foreach": True}
        if net_arch is None and kwargs.get("features_extractor_class") is not NatureCNN:
            net_arch = dict(pi=[64, 64], vf=[64])
        if not is_int(n_state_action_pairs) or n_state_action_pairs < 0:
            raise ValueError(f"n_state_action_pairs must be an int >= 0, got {n_state_action_pairs!r}")
        if representation == "spr" and n_state_action_pairs == 0:
            raise ValueError("representation='spr' needs n_state_action_pairs > 0")
        if has_image(observation_space):
            n_state_action_pairs = 0
        self.representation_name = representation
        self.embedding_dim = embedding_dim
        representation_kwargs = check_dict("representation_kwargs", representation_kwargs)
        objective_kwargs = check_dict("objective_kwargs", objective_kwargs)
        if isinstance(representation_objectives, str):  # "cl" means ("cl",), not ("c", "l")
            representation_objectives = (representation_objectives,)
        if "aux" in representation_objectives:
            _check_aux(observation_space, n_state_action_pairs)
        self.representation_kwargs = representation_kwargs
        self.n_state_action_pairs = int(n_state_action_pairs)
        self.critic_embedding_arch = list(check_layer_sizes("critic_embedding_arch", critic_embedding_arch))
        self.critic_head_arch = list(check_layer_sizes("critic_head_arch", critic_head_arch))
        self.critic_combine = critic_combine
        self.critic_activation_fn = critic_activation_fn
        self.chi_normalization = chi_normalization
        self.representation_objectives = tuple(representation_objectives)
        _check_objectives(self.representation_objectives, objective_kwargs)
        self.objective_kwargs = {name: dict(value) for name, value in objective_kwargs.items()}
        #: False inside :meth:`critic_frozen`: values carry no gradient
        self.critic_trainable = True
        #: False: chi of the behaviour policy carries no gradient even while the critic trains (cached, so the value
        #: loss on the rollout leaves the encoder alone); the algorithm's ``rollout_encoder_gradient`` sets it
        self.behaviour_chi_gradient = True
        self._embedding_cache: tuple[tuple, th.Tensor] | None = None
        super().__init__(observation_space, action_space, lr_schedule, net_arch, activation_fn, *args, **kwargs)

    def _build(self, lr_schedule: Schedule) -> None:
        super()._build(lr_schedule)
        self.mean_activation = nn.Identity() if self.mean_activation_fn is None else self.mean_activation_fn()
        self.layout = ActorLayout.from_policy(self)
        self.representation: PolicyRepresentation = make_representation(
            self.representation_name,
            self.layout,
            self.observation_space,
            self.action_space,
            self.embedding_dim,
            **self.representation_kwargs,
        )
        self.value_net = PeVFAValueHead(
            self.mlp_extractor.latent_dim_vf,
            self.representation.embedding_dim,
            self.critic_embedding_arch,
            self.critic_head_arch,
            self.critic_combine,
            self.critic_activation_fn or self.activation_fn,
            self.chi_normalization,
        )
        if self.ortho_init:
            self.value_net.init_weights(self.init_weights)
        if self.weight_init == "normal_fan_in":  # before the objectives copy the encoder (CL's key encoder)
            init_normal_fan_in(self)
        self.code_dim = self.embedding_dim if self.representation.uses_codes else 0
        self.objectives = nn.ModuleDict(
            {
                name: make_objective(
                    name, self.representation, self.observation_space, self.action_space, **self.objective_kwargs.get(name, {})
                )
                for name in self.representation_objectives
            }
        )
        #: Pairs each record holds: none where neither the representation nor an objective reads them, twice
        #: ``n_state_action_pairs`` where SPR and AUX read pairs of their own
        n_pairs, aux = self.n_state_action_pairs, dict(self.objectives).get("aux")
        reads_pairs = self.representation.uses_state_action_pairs or aux is not None
        self.n_recorded_pairs = n_pairs if reads_pairs else 0
        if self.representation.uses_state_action_pairs and aux is not None and aux.separate_pairs:
            self.n_recorded_pairs = 2 * n_pairs
            self.representation.pairs, aux.pairs = slice(0, n_pairs), slice(n_pairs, 2 * n_pairs)
            for module in self.objectives.modules():  # copies of the encoder (CL's momentum key encoder) read as it does
                if isinstance(module, PolicyRepresentation):
                    module.pairs = self.representation.pairs
        # The behaviour policy's record travels with the policy's state dict (empty fields stay out of it).
        behaviour = {
            "behaviour_params": th.zeros(self.layout.n_params),
            "behaviour_states": th.zeros(self.n_recorded_pairs, state_dim(self.observation_space)),
            "behaviour_actions": th.zeros(self.n_recorded_pairs, get_action_dim(self.action_space)),
            "behaviour_codes": th.zeros(self.code_dim),
            "has_behaviour": th.zeros(()),  # 1.0 once a record was set (a float: SB3's tests randomise state dicts)
        }
        for name, tensor in behaviour.items():
            self.register_buffer(name, tensor, persistent=tensor.numel() > 0)
        excluded = {id(p) for p in [*self.critic_parameters(), *self.objectives.parameters()]}
        log_std = getattr(self, "log_std", None)
        own_log_std_group = self.log_std_lr_scale != 1.0 and isinstance(log_std, nn.Parameter)
        if own_log_std_group:
            excluded.add(id(log_std))
        groups = [
            {"params": [p for p in self.parameters() if id(p) not in excluded], "name": "actor"},
            {"params": list(self.critic_parameters()), "name": "critic"},
        ]
        if own_log_std_group:
            groups.append({"params": [log_std], "name": "log_std", "lr_scale": self.log_std_lr_scale})
        for group in groups:
            group["lr"] = lr_schedule(1) * group.get("lr_scale", 1.0)
        self.optimizer = self.optimizer_class(groups, lr=lr_schedule(1), **self.optimizer_kwargs)  # type: ignore[call-arg]
        # One optimizer per objective: the shared encoder and the objective's own modules, at the objective's rate.
        for name, objective in self.objectives.items():
            params = [*self.representation.parameters(), *(p for p in objective.parameters() if p.requires_grad)]
            optimizer = self.optimizer_class(params, lr=objective.learning_rate, **self.optimizer_kwargs)  # type: ignore[call-arg]
            setattr(self, f"{name}_optimizer", optimizer)

    def critic_parameters(self) -> Iterator[nn.Parameter]:
        """Parameters trained by the value loss only: state stream, embedding stream, head and representation.

        A shared features extractor belongs to the actor group (as in SB3, it gets both losses)."""
        modules: list[nn.Module] = [self.mlp_extractor.value_net, self.value_net, self.representation]
        if not self.share_features_extractor:
            modules.append(self.vf_features_extractor)
        for module in modules:
            yield from module.parameters()

    def _get_constructor_parameters(self) -> dict[str, Any]:
        data = super()._get_constructor_parameters()
        data.update(
            representation=self.representation_name,
            embedding_dim=self.embedding_dim,
            representation_kwargs=self.representation_kwargs,
            n_state_action_pairs=self.n_state_action_pairs,
            critic_embedding_arch=self.critic_embedding_arch,
            critic_head_arch=self.critic_head_arch,
            critic_combine=self.critic_combine,
            critic_activation_fn=self.critic_activation_fn,
            chi_normalization=self.chi_normalization,
            representation_objectives=self.representation_objectives,
            objective_kwargs=self.objective_kwargs,
            mean_activation_fn=self.mean_activation_fn,
            weight_init=self.weight_init,
            log_std_lr_scale=self.log_std_lr_scale,
        )
        return data

    def _get_action_dist_from_latent(self, latent_pi: th.Tensor):
        """SB3's, the Gaussian's mean through ``mean_activation_fn`` where one is set."""
        if self.mean_activation_fn is None:
            return super()._get_action_dist_from_latent(latent_pi)
        return self.action_dist.proba_distribution(self.mean_activation(self.action_net(latent_pi)), self.log_std)

    # ------------------------------------------------------------------ the critic V(s, chi)
    def _latents(self, obs: PyTorchObs) -> tuple[th.Tensor, th.Tensor]:
        features = self.extract_features(obs)
        if self.share_features_extractor:
            return self.mlp_extractor(features)
        return self.mlp_extractor.forward_actor(features[0]), self.mlp_extractor.forward_critic(features[1])

    def _values(self, latent_vf: th.Tensor, chi: th.Tensor | None) -> th.Tensor:
        chi = self.behaviour_embedding() if chi is None else chi
        if not self.critic_trainable:
            with th.no_grad():
                return self.value_net(latent_vf.detach(), chi.detach())
        return self.value_net(latent_vf, chi)

    def forward(
        self, obs: th.Tensor, deterministic: bool = False, chi: th.Tensor | None = None
    ) -> tuple[th.Tensor, th.Tensor, th.Tensor]:
        """SB3's forward (actions, values, log-probabilities) with values V(s, chi).

        :param chi: Embedding ``(1 or batch, embedding_dim)`` of the policy whose values are wanted
            (default: the behaviour policy's)
        """
        latent_pi, latent_vf = self._latents(obs)
        values = self._values(latent_vf, chi)
        distribution = self._get_action_dist_from_latent(latent_pi)
        actions = distribution.get_actions(deterministic=deterministic)
        log_prob = distribution.log_prob(actions)
        actions = actions.reshape((-1, *self.action_space.shape))  # type: ignore[misc]
        return actions, values, log_prob

    def evaluate_actions(
        self, obs: PyTorchObs, actions: th.Tensor, chi: th.Tensor | None = None
    ) -> tuple[th.Tensor, th.Tensor, th.Tensor | None]:
        """SB3's evaluate_actions (values, log-probabilities, entropy) with values V(s, chi).

        :param chi: As in :meth:`forward`; in training mode the behaviour policy's chi is recomputed with gradient,
            so the value loss trains the encoder (E2E), unless :attr:`behaviour_chi_gradient` is False (the algorithm's
            ``rollout_encoder_gradient``): then it is the cached chi, without gradient
        """
        latent_pi, latent_vf = self._latents(obs)
        values = self._values(latent_vf, chi)
        distribution = self._get_action_dist_from_latent(latent_pi)
        return values, distribution.log_prob(actions), distribution.entropy()

    def predict_values(self, obs: PyTorchObs, chi: th.Tensor | None = None) -> th.Tensor:
        """V(s, chi), ``(batch, 1)``.

        :param chi: Embeddings ``(batch, embedding_dim)`` matching ``obs`` (e.g. of many historical policies), or one
            ``(1, embedding_dim)`` broadcast to all; default: the behaviour policy's
        """
        features = super(ActorCriticPolicy, self).extract_features(obs, self.vf_features_extractor)
        return self._values(self.mlp_extractor.forward_critic(features), chi)

    @contextmanager
    def critic_frozen(self) -> Iterator[None]:
        """Within this context values carry no gradient (the paper's order: the actor update after the critic's)."""
        self.critic_trainable = False
        self.clear_embedding_cache()
        try:
            yield
        finally:
            self.critic_trainable = True
            self.clear_embedding_cache()

    # ------------------------------------------------------------------ policy embeddings
    def embed(self, records: PolicyRecord) -> th.Tensor:
        """chi of ``P`` recorded policies, ``(P, embedding_dim)``."""
        return self.representation(records)

    def observe_rollout(self, buffer: RolloutBuffer) -> None:
        """Hand the rows of a complete rollout that the representation reads (:meth:`PolicyRepresentation.rollout_rows`,
        e.g. to set learned inputs of its own from the first rollout) to it as the actor's inputs (after
        ``preprocess_obs`` and the actor's features extractor); where it reads none, nothing is done.

        :param buffer: The rollout, before SB3's ``get`` flattens it: observations ``(n_steps, n_envs, ...)``
        """
        index = self.representation.rollout_rows(buffer.buffer_size * buffer.n_envs)
        if index is None:
            return
        envs, steps = np.divmod(index, buffer.buffer_size)  # env-major rows
        observations = obs_as_tensor(rows(buffer.observations, (steps, envs)), self.device)
        with th.no_grad():
            features = super(ActorCriticPolicy, self).extract_features(observations, self.pi_features_extractor)
        self.representation.observe_rollout(features)
        self.clear_embedding_cache()

    def set_behaviour_record(self, record: PolicyRecord) -> None:
        """Make the critic evaluate, by default, the policy of ``record`` (one policy, ``P == 1``)."""
        with th.no_grad():
            self.behaviour_params.copy_(record.params[0])
            self.behaviour_states.copy_(record.states[0])
            self.behaviour_actions.copy_(record.actions[0])
            self.behaviour_codes.copy_(record.codes[0])
            self.has_behaviour.fill_(1.0)
        self.clear_embedding_cache()

    def behaviour_record(self) -> PolicyRecord:
        """The behaviour policy's record; before any record, one of the live actor's parameters."""
        if not bool(self.has_behaviour):
            if self.representation.uses_state_action_pairs or self.representation.uses_codes:
                raise RuntimeError(
                    f"representation={self.representation_name!r} needs a recorded policy: train first, or call "
                    "set_behaviour_record() with a record of the policy history"
                )
            params = self.layout.flatten(self).unsqueeze(0)
            return PolicyRecord(params, self.behaviour_states[None], self.behaviour_actions[None], self.behaviour_codes[None])
        return PolicyRecord(
            self.behaviour_params[None], self.behaviour_states[None], self.behaviour_actions[None], self.behaviour_codes[None]
        )

    def behaviour_embedding(self) -> th.Tensor:
        """chi of the behaviour policy, ``(1, embedding_dim)``: recomputed (with gradient) while the critic trains
        (unless :attr:`behaviour_chi_gradient` is False), cached otherwise (rollouts, evaluation, frozen critic),
        computed with the representation in evaluation mode (SPR: all pairs)."""
        if self.training and self.critic_trainable and self.behaviour_chi_gradient:
            return self.embed(self.behaviour_record())
        key = self._embedding_key()
        if self._embedding_cache is None or self._embedding_cache[0] != key:
            representation_mode = self.representation.training
            self.representation.train(False)  # the cached chi reads all of SPR's pairs, as the rollout's values did
            try:
                with th.no_grad():
                    embedding = self.embed(self.behaviour_record())
            finally:
                self.representation.train(representation_mode)
            if not bool(self.has_behaviour):
                return embedding
            self._embedding_cache = (key, embedding)
        return self._embedding_cache[1]

    def _embedding_key(self) -> tuple[tuple[int, int], ...]:
        """What the cached chi was computed from: the encoder's parameters and buffers and the behaviour record, each
        by its storage and version, so that any write to them (an optimizer step, ``load_from_vector``, ``.to()``, an
        edit in place) makes the cache miss."""
        tensors = [*self.representation.parameters(), *self.representation.buffers(), self.behaviour_params,
                   self.behaviour_states, self.behaviour_actions, self.behaviour_codes, self.has_behaviour]  # fmt: skip
        return tuple((tensor.data_ptr(), tensor._version) for tensor in tensors)

    def clear_embedding_cache(self) -> None:
        self._embedding_cache = None

    def load_state_dict(self, *args: Any, **kwargs: Any):  # type: ignore[override]
        """``nn.Module.load_state_dict``; the cached chi of the old weights is dropped."""
        result = super().load_state_dict(*args, **kwargs)
        self.clear_embedding_cache()
        return result

    def __getstate__(self) -> dict[str, Any]:
        """What pickle and ``copy.deepcopy`` take: the module without the action distribution of the latest call.

        That distribution is a by-product (each call builds a new one) and, after a training step, holds tensors of the
        autograd graph, which torch refuses to deepcopy: SB3's own policies cannot be deepcopied after ``learn()``."""
        state = dict(super().__getstate__())
        action_dist = copy.copy(self.action_dist)
        for name, value in vars(action_dist).items():
            values = value if isinstance(value, list) else [value]
            if any(isinstance(v, th.distributions.Distribution) for v in values):
                setattr(action_dist, name, None)  # rebuilt at the next call
            elif isinstance(value, th.Tensor) and value.grad_fn is not None:
                setattr(action_dist, name, value.detach().clone())  # e.g. gSDE's exploration matrices
        state["action_dist"] = action_dist
        return state


class PeVFAActorCriticCnnPolicy(PeVFAActorCriticPolicy):
    """CNN policy (NatureCNN features). OPR encodes the actor's MLP head (``policy_net`` and ``action_net``)."""

    def __init__(self, *args: Any, features_extractor_class: type = NatureCNN, **kwargs: Any):
        super().__init__(*args, features_extractor_class=features_extractor_class, **kwargs)


class PeVFAMultiInputActorCriticPolicy(PeVFAActorCriticPolicy):
    """Policy for Dict observations (CombinedExtractor features)."""

    def __init__(self, *args: Any, features_extractor_class: type = CombinedExtractor, **kwargs: Any):
        super().__init__(*args, features_extractor_class=features_extractor_class, **kwargs)


#: SB3's names, which every PeVFA algorithm's ``policy_aliases`` maps
MlpPolicy = PeVFAActorCriticPolicy
CnnPolicy = PeVFAActorCriticCnnPolicy
MultiInputPolicy = PeVFAMultiInputActorCriticPolicy
