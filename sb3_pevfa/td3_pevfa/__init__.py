from sb3_pevfa.td3_pevfa.policies import MlpPolicy, TD3PeVFAPolicy
from sb3_pevfa.td3_pevfa.td3_pevfa import TD3PeVFA

__all__ = ["MlpPolicy", "TD3PeVFA", "TD3PeVFAPolicy"]
