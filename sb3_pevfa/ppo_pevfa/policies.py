"""The policies of PPOPeVFA (SB3's names for the PeVFA actor-critic policies)."""

from sb3_pevfa.pevfa.policies import CnnPolicy, MlpPolicy, MultiInputPolicy, PeVFAActorCriticPolicy

__all__ = ["CnnPolicy", "MlpPolicy", "MultiInputPolicy", "PeVFAActorCriticPolicy"]
