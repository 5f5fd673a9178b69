from sb3_pevfa.td3_pevfa.policies import (
    CnnPolicy,
    MlpPolicy,
    MultiInputPolicy,
    TD3PeVFACnnPolicy,
    TD3PeVFAMultiInputPolicy,
    TD3PeVFAPolicy,
)
from sb3_pevfa.td3_pevfa.td3_pevfa import TD3PeVFA

__all__ = [
    "CnnPolicy",
    "MlpPolicy",
    "MultiInputPolicy",
    "TD3PeVFA",
    "TD3PeVFACnnPolicy",
    "TD3PeVFAMultiInputPolicy",
    "TD3PeVFAPolicy",
]
