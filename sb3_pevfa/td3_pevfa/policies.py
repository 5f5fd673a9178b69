"""TD3's policies with a policy-extended twin critic Q(s, a, chi_pi)."""

from typing import Any

import torch as th
from stable_baselines3.common.torch_layers import BaseFeaturesExtractor, CombinedExtractor, NatureCNN
from stable_baselines3.td3.policies import TD3Policy
from torch import nn

from sb3_pevfa.pevfa.q_critics import PeVFAQPolicyMixin


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


class TD3PeVFACnnPolicy(TD3PeVFAPolicy):
    """:class:`TD3PeVFAPolicy` for images (SB3's ``NatureCNN``), as SB3's TD3 ``CnnPolicy``; the CNN is not part of a
    snapshot (the layout records the actor's linear layers)."""

    def __init__(self, *args: Any, features_extractor_class: type[BaseFeaturesExtractor] = NatureCNN, **kwargs: Any):
        super().__init__(*args, features_extractor_class=features_extractor_class, **kwargs)


class TD3PeVFAMultiInputPolicy(TD3PeVFAPolicy):
    """:class:`TD3PeVFAPolicy` for Dict observations (SB3's ``CombinedExtractor``), as SB3's TD3 ``MultiInputPolicy``."""

    def __init__(self, *args: Any, features_extractor_class: type[BaseFeaturesExtractor] = CombinedExtractor, **kwargs: Any):
        super().__init__(*args, features_extractor_class=features_extractor_class, **kwargs)


MlpPolicy = TD3PeVFAPolicy
CnnPolicy = TD3PeVFACnnPolicy
MultiInputPolicy = TD3PeVFAMultiInputPolicy
