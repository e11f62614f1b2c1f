"""UW-3DGS's depth-consistency loss L_z: for every visible Gaussian whose centre projects inside the image,
|rendered range at that pixel - the centre's distance to the camera|, in units of the median of those rendered
ranges (unit-free: the weight means the same at any scene scale), weighted per Gaussian, averaged.

`depth_consistency` is the PyTorch reference (and the path on CUDA); `kernel="compiled"` runs it as one pass of the
compiled CPU backend (`uw3dgs/render/csrc/depth_consistency.cpp`) for CPU tensors of float32 or float64: the same
numbers to float rounding (tests/test_metrics.py), a dozen fewer passes over the Gaussians."""

from __future__ import annotations

from typing import Literal

import torch
from torch import Tensor
from torch.autograd.function import once_differentiable

from uw3dgs.render import cpu_backend


def depth_consistency(ranges: Tensor, means: Tensor, means2d: Tensor, radii: Tensor, center: Tensor,
                      weights: Tensor | None = None, kernel: Literal["compiled", "torch"] = "compiled") -> Tensor:
    """L_z (a scalar) of one view: ranges [H, W] the rendered range (world units), means [N, 3] the Gaussian centres,
    means2d [N, 2] their pixel positions (no gradient is taken), radii [N] (0: not visible), center [3] the camera
    centre, weights [N] per Gaussian (None: 1). Gradients reach `ranges` and `means`; 0 (with a graph) when no
    centre projects inside the image."""
    height, width = ranges.shape
    if kernel == "compiled" and cpu_backend.runs_on(means) and ranges.dtype == means.dtype:
        dtype = means.dtype
        weights = means.new_empty(0) if weights is None else weights.detach().to(dtype).contiguous()
        return _DepthConsistency.apply(ranges.contiguous(), means.contiguous(), means2d.detach().to(dtype).contiguous(),
                                       radii.to(torch.int32).contiguous(), center.detach().to(dtype).contiguous(),
                                       weights)
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


class _DepthConsistency(torch.autograd.Function):
    @staticmethod
    def forward(ctx, ranges, means, means2d, radii, center, weights):
        loss, gauss, pixel, coef = cpu_backend.load_extension().depth_consistency_forward(radii, means2d, means,
                                                                                          center, ranges, weights)
        ctx.save_for_backward(means, center, ranges, gauss, pixel, coef)
        return loss

    @staticmethod
    @once_differentiable
    def backward(ctx, grad):
        means, center, ranges, gauss, pixel, coef = ctx.saved_tensors
        g_ranges, g_means = cpu_backend.load_extension().depth_consistency_backward(means, center, ranges, gauss,
                                                                                    pixel, coef, float(grad))
        return g_ranges, g_means, None, None, None, None
