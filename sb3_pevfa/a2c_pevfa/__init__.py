from sb3_pevfa.a2c_pevfa.a2c_pevfa import A2CPeVFA
from sb3_pevfa.a2c_pevfa.policies import CnnPolicy, MlpPolicy, MultiInputPolicy

__all__ = ["A2CPeVFA", "CnnPolicy", "MlpPolicy", "MultiInputPolicy"]
