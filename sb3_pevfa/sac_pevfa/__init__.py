from sb3_pevfa.sac_pevfa.policies import MlpPolicy, MultiInputPolicy, SACPeVFAMultiInputPolicy, SACPeVFAPolicy
from sb3_pevfa.sac_pevfa.sac_pevfa import SACPeVFA

__all__ = ["MlpPolicy", "MultiInputPolicy", "SACPeVFA", "SACPeVFAMultiInputPolicy", "SACPeVFAPolicy"]
