from sb3_pevfa.sac_pevfa.policies import (
    CnnPolicy,
    MlpPolicy,
    MultiInputPolicy,
    SACPeVFACnnPolicy,
    SACPeVFAMultiInputPolicy,
    SACPeVFAPolicy,
)
from sb3_pevfa.sac_pevfa.sac_pevfa import SACPeVFA

__all__ = [
    "CnnPolicy",
    "MlpPolicy",
    "MultiInputPolicy",
    "SACPeVFA",
    "SACPeVFACnnPolicy",
    "SACPeVFAMultiInputPolicy",
    "SACPeVFAPolicy",
]
