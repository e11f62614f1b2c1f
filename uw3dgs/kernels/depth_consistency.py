"""UW-3DGS's depth-consistency loss L_z (`depth_consistency.cpp`) in one pass with its backward to the rendered
ranges and the means; the contract and the PyTorch reference are `uw3dgs.methods.uw3dgs.depth_consistency`."""

from __future__ import annotations

import torch
from torch import Tensor
from torch.autograd.function import once_differentiable

from uw3dgs.kernels.build import extension


class DepthConsistency(torch.autograd.Function):
    @staticmethod
    def forward(ctx, ranges, means, means2d, radii, center, weights):
        loss, gauss, pixel, coef = extension().depth_consistency_forward(radii, means2d, means,
                                                                                          center, ranges, weights)
        ctx.save_for_backward(means, center, ranges, gauss, pixel, coef)
        return loss

    @staticmethod
    @once_differentiable
    def backward(ctx, grad):
        means, center, ranges, gauss, pixel, coef = ctx.saved_tensors
        g_ranges, g_means = extension().depth_consistency_backward(means, center, ranges, gauss,
                                                                                    pixel, coef, float(grad))
        return g_ranges, g_means, None, None, None, None


def depth_consistency(ranges: Tensor, means: Tensor, means2d: Tensor, radii: Tensor, center: Tensor,
                      weights: Tensor) -> Tensor:
    """L_z of contiguous CPU tensors of one float dtype (radii int32; weights [N] or empty for 1): the same numbers
    as the reference to float rounding."""
    return DepthConsistency.apply(ranges, means, means2d, radii, center, weights)
