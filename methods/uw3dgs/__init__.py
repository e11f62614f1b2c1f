"""`uw3dgs`, the paper's method, `uw3dgs-paper`, the paper's text where the project departs from it, and the
ablations of both: the model (`model.py`), what only it owns beside it (Physics-Aware Uncertainty Pruning in `paup/`,
the depth-consistency loss L_z in `depth_consistency.py`)."""

from uw3dgs.methods.uw3dgs.model import (
    ABLATIONS,
    UW3DGSModel,
    UW3DGSModelConfig,
    ablation,
    method,
    no_lbeta,
    no_lz,
    no_medium,
    no_paup,
    paper,
    paper_no_lbeta,
    paper_no_lz,
    paper_no_medium,
    paper_no_paup,
    preset,
    uw3dgs_optimizers,
)

__all__ = ["ABLATIONS", "UW3DGSModel", "UW3DGSModelConfig", "ablation", "method", "no_lbeta", "no_lz", "no_medium",
           "no_paup", "paper", "paper_no_lbeta", "paper_no_lz", "paper_no_medium", "paper_no_paup", "preset",
           "uw3dgs_optimizers"]
