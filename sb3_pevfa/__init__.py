import os

import sb3_pevfa.envs  # noqa: F401  (registers PointWalker-v0)
from sb3_pevfa.a2c_pevfa import A2CPeVFA
from sb3_pevfa.pevfa import PAPER_SCHEDULE, REPRESENTATIONS, PolicyHistory, PolicyHistoryCallback, PolicyRecord
from sb3_pevfa.ppo_pevfa import PPOPeVFA
from sb3_pevfa.sac_pevfa import SACPeVFA
from sb3_pevfa.td3_pevfa import TD3PeVFA

# Read version from file
version_file = os.path.join(os.path.dirname(__file__), "version.txt")
with open(version_file) as file_handler:
    __version__ = file_handler.read().strip()

__all__ = [
    "PAPER_SCHEDULE",
    "REPRESENTATIONS",
    "A2CPeVFA",
    "PPOPeVFA",
    "PolicyHistory",
    "PolicyHistoryCallback",
    "PolicyRecord",
    "SACPeVFA",
    "TD3PeVFA",
]
