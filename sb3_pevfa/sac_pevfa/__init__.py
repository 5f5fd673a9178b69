from sb3_pevfa.sac_pevfa.policies import MlpPolicy, SACPeVFAPolicy
from sb3_pevfa.sac_pevfa.sac_pevfa import SACPeVFA

__all__ = ["MlpPolicy", "SACPeVFA", "SACPeVFAPolicy"]
