"""The PeVFA feature: policy records, representations, objectives, the history, the recorder, the critic and the
algorithm mixin that PPOPeVFA and A2CPeVFA share (see docs/architecture.md)."""

from sb3_pevfa.pevfa.algorithm import PeVFAAlgorithm
from sb3_pevfa.pevfa.arguments import PAPER_SCHEDULE
from sb3_pevfa.pevfa.callbacks import PolicyHistoryCallback
from sb3_pevfa.pevfa.history import PolicyHistory
from sb3_pevfa.pevfa.policies import PeVFAActorCriticPolicy
from sb3_pevfa.pevfa.recorder import PolicyRecorder
from sb3_pevfa.pevfa.records import PolicyRecord
from sb3_pevfa.pevfa.representations import REPRESENTATIONS

__all__ = [
    "PAPER_SCHEDULE",
    "REPRESENTATIONS",
    "PeVFAActorCriticPolicy",
    "PeVFAAlgorithm",
    "PolicyHistory",
    "PolicyHistoryCallback",
    "PolicyRecord",
    "PolicyRecorder",
]
