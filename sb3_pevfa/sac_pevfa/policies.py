"""SAC's policies with a policy-extended twin critic Q(s, a, chi_pi)."""

import torch as th
from stable_baselines3.sac.policies import SACPolicy
from torch import nn

from sb3_pevfa.pevfa.q_critics import CnnPolicyMixin, MultiInputPolicyMixin, PeVFAQPolicyMixin


class SACPeVFAPolicy(PeVFAQPolicyMixin, SACPolicy):
    """SB3's :class:`~stable_baselines3.sac.policies.SACPolicy`, its critics Q(s, a, chi)
    (:class:`~sb3_pevfa.pevfa.q_critics.PeVFAQPolicyMixin` lists the PeVFA arguments); the actor is SB3's. OPR reads
    ``latent_pi``, then the ``mu`` and ``log_std`` heads."""

    def actor_parts(self) -> tuple[nn.Module, list[nn.Module]]:
        """The actor's hidden layers and its output heads (the mean and the log-std), as the layout reads them."""
        return self.actor.latent_pi, [self.actor.mu, self.actor.log_std]

    def deterministic_actions(self, features: th.Tensor) -> th.Tensor:
        """The actor's deterministic actions (its squashed mean) at its features, as SB3's actor computes them."""
        return th.tanh(self.actor.mu(self.actor.latent_pi(features)))


class SACPeVFACnnPolicy(CnnPolicyMixin, SACPeVFAPolicy):
    """:class:`SACPeVFAPolicy` for images, as SB3's SAC ``CnnPolicy``."""


class SACPeVFAMultiInputPolicy(MultiInputPolicyMixin, SACPeVFAPolicy):
    """:class:`SACPeVFAPolicy` for Dict observations, as SB3's SAC ``MultiInputPolicy``."""


MlpPolicy = SACPeVFAPolicy
CnnPolicy = SACPeVFACnnPolicy
MultiInputPolicy = SACPeVFAMultiInputPolicy
