"""`uw3dgs`, the paper's method, and its ablations: the model (`model.py`), what only it owns beside it
(Physics-Aware Uncertainty Pruning in `paup/`, the depth-consistency loss L_z in `depth_consistency.py`)."""

from uw3dgs.methods.uw3dgs.model import (
    UW3DGSModel,
    UW3DGSModelConfig,
    method,
    no_lbeta,
    no_lz,
    no_medium,
    no_paup,
    uw3dgs_optimizers,
)

__all__ = ["UW3DGSModel", "UW3DGSModelConfig", "method", "no_lbeta", "no_lz", "no_medium", "no_paup",
           "uw3dgs_optimizers"]
