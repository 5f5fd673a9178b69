"""TD3's policies with a policy-extended twin critic Q(s, a, chi_pi)."""

import torch as th
from stable_baselines3.td3.policies import TD3Policy
from torch import nn

from sb3_pevfa.pevfa.q_critics import CnnPolicyMixin, MultiInputPolicyMixin, PeVFAQPolicyMixin


class TD3PeVFAPolicy(PeVFAQPolicyMixin, TD3Policy):
    """SB3's :class:`~stable_baselines3.td3.policies.TD3Policy`, its critics Q(s, a, chi)
    (:class:`~sb3_pevfa.pevfa.q_critics.PeVFAQPolicyMixin` lists the PeVFA arguments); the actor is SB3's. OPR reads
    the layers of ``mu`` (its last one the output, through SB3's tanh)."""

    #: The actor's output goes through a tanh (SB3's ``squash_output``), as the layout evaluates it
    mean_activation_fn = nn.Tanh

    def actor_parts(self) -> tuple[nn.Module, list[nn.Module]]:
        """The actor's hidden layers and its output layer (before the tanh), as the layout reads them."""
        layers = list(self.actor.mu)
        if not isinstance(layers[-1], nn.Tanh):
            raise TypeError(f"TD3PeVFA expects SB3's actor, its output through nn.Tanh, got {self.actor.mu}")
        return nn.Sequential(*layers[:-2]), [layers[-2]]

    def deterministic_actions(self, features: th.Tensor) -> th.Tensor:
        """The actor's actions at its features, as SB3's actor computes them."""
        return self.actor.mu(features)


class TD3PeVFACnnPolicy(CnnPolicyMixin, TD3PeVFAPolicy):
    """:class:`TD3PeVFAPolicy` for images, as SB3's TD3 ``CnnPolicy``."""


class TD3PeVFAMultiInputPolicy(MultiInputPolicyMixin, TD3PeVFAPolicy):
    """:class:`TD3PeVFAPolicy` for Dict observations, as SB3's TD3 ``MultiInputPolicy``."""


MlpPolicy = TD3PeVFAPolicy
CnnPolicy = TD3PeVFACnnPolicy
MultiInputPolicy = TD3PeVFAMultiInputPolicy
