from sb3_pevfa.td3_pevfa.policies import MlpPolicy, MultiInputPolicy, TD3PeVFAMultiInputPolicy, TD3PeVFAPolicy
from sb3_pevfa.td3_pevfa.td3_pevfa import TD3PeVFA

__all__ = ["MlpPolicy", "MultiInputPolicy", "TD3PeVFA", "TD3PeVFAMultiInputPolicy", "TD3PeVFAPolicy"]
