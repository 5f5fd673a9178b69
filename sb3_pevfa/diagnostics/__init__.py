"""Diagnostics of the paper: local and global value generalization, embedding maps, zero-shot policy values.

They need the ``diagnostics`` extra (``pip install -e ".[diagnostics]"`` in the repository's checkout)."""

from sb3_pevfa.extras import require_extra

require_extra("diagnostics", "sb3_pevfa.diagnostics", modules=("scipy",))  # the others are imported where used


from sb3_pevfa.diagnostics.embedding_maps import plot_embedding_maps, policy_embeddings
from sb3_pevfa.diagnostics.global_generalization import plot_global_generalization, run_global_generalization
from sb3_pevfa.diagnostics.local_generalization import LocalGeneralizationCallback, plot_local_generalization
from sb3_pevfa.diagnostics.q_local_generalization import QLocalGeneralizationCallback
from sb3_pevfa.diagnostics.zero_shot import predict_policy_values

__all__ = [
    "LocalGeneralizationCallback",
    "QLocalGeneralizationCallback",
    "plot_embedding_maps",
    "plot_global_generalization",
    "plot_local_generalization",
    "policy_embeddings",
    "predict_policy_values",
    "run_global_generalization",
]
