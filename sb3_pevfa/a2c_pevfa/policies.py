"""The policies of A2CPeVFA (SB3's names for the PeVFA actor-critic policies)."""

from sb3_pevfa.pevfa.policies import (
    PeVFAActorCriticCnnPolicy,
    PeVFAActorCriticPolicy,
    PeVFAMultiInputActorCriticPolicy,
)

MlpPolicy = PeVFAActorCriticPolicy
CnnPolicy = PeVFAActorCriticCnnPolicy
MultiInputPolicy = PeVFAMultiInputActorCriticPolicy

__all__ = ["CnnPolicy", "MlpPolicy", "MultiInputPolicy", "PeVFAActorCriticPolicy"]
