"""Physics-Aware Uncertainty Pruning (PAUP, the paper's second contribution): per-Gaussian statistics from nearby
views, a learned floater probability, the relaxed keep mask the training render uses, and hard pruning (at
density-control events, or every N steps as the paper writes it). The reading of the paper is in
docs/methods/uw3dgs.md ("PAUP")."""

from uw3dgs.methods.uw3dgs.paup.branch import PAUP, PAUPConfig
from uw3dgs.methods.uw3dgs.paup.scorer import FloaterScorer, relaxed_keep_mask
from uw3dgs.methods.uw3dgs.paup.statistics import ViewObservation, combine_views, observe_view

__all__ = ["PAUP", "FloaterScorer", "PAUPConfig", "ViewObservation", "combine_views", "observe_view",
           "relaxed_keep_mask"]
