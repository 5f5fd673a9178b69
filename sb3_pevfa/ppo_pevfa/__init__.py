from sb3_pevfa.ppo_pevfa.policies import CnnPolicy, MlpPolicy, MultiInputPolicy
from sb3_pevfa.ppo_pevfa.ppo_pevfa import PPOPeVFA

__all__ = ["CnnPolicy", "MlpPolicy", "MultiInputPolicy", "PPOPeVFA"]
