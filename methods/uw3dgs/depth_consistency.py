"""UW-3DGS's depth-consistency loss L_z: for every visible Gaussian whose centre projects inside the image,
|rendered range at that pixel - the centre's distance to the camera|, in units of the median of those rendered
ranges (unit-free: the weight means the same at any scene scale), weighted per Gaussian, averaged.

`depth_consistency` is the PyTorch reference (and the path on CUDA); `kernel="compiled"` runs it as one pass of the
compiled CPU kernels (`uw3dgs/kernels/depth_consistency.cpp`) for CPU tensors of float32 or float64: the same
numbers to float rounding (tests/test_metrics.py), a dozen fewer passes over the Gaussians."""

from __future__ import annotations

import torch
from torch import Tensor

from uw3dgs.kernels import depth_consistency as compiled
from uw3dgs.kernels.policy import Kernels, use_compiled


def depth_consistency(ranges: Tensor, means: Tensor, means2d: Tensor, radii: Tensor, center: Tensor,
                      weights: Tensor | None = None, kernel: Kernels = "compiled") -> Tensor:
    """L_z (a scalar) of one view: ranges [H, W] the rendered range (world units), means [N, 3] the Gaussian centres,
    means2d [N, 2] their pixel positions (no gradient is taken), radii [N] (0: not visible), center [3] the camera
    centre, weights [N] per Gaussian (None: 1). Gradients reach `ranges` and `means`; 0 (with a graph) when no
    centre projects inside the image."""
    height, width = ranges.shape
    if use_compiled(kernel, means) and ranges.dtype == means.dtype:
        dtype = means.dtype
        weights = means.new_empty(0) if weights is None else weights.detach().to(dtype).contiguous()
        return compiled.depth_consistency(ranges.contiguous(), means.contiguous(),
                                          means2d.detach().to(dtype).contiguous(), radii.to(torch.int32).contiguous(),
                                          center.detach().to(dtype).contiguous(), weights)
    visible = (radii > 0).nonzero().squeeze(1)
    pix = means2d.detach().index_select(0, visible).floor().long()
    inside = (pix[:, 0] >= 0) & (pix[:, 0] < width) & (pix[:, 1] >= 0) & (pix[:, 1] < height)
    if not bool(inside.any()):
        return ranges.sum() * 0.0
    # one gather per tensor (index_select, whose backward is an index_add): no boolean-mask copies
    picked, pix = visible[inside], pix[inside]
    rendered = ranges.reshape(-1).index_select(0, pix[:, 1] * width + pix[:, 0])
    own = (means.index_select(0, picked) - center).norm(dim=-1)
    scale = rendered.detach().median().clamp_min(1e-6)
    error = (rendered - own).abs() / scale
    return error.mean() if weights is None else (weights.index_select(0, picked) * error).mean()
