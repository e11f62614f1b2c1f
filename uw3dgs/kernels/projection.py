"""The projection stage (`projection.cpp`): 3D Gaussians to screen-space means, conics, depths and radii, with its
hand-written backward to means, quats and scales."""

from __future__ import annotations

import torch
from torch import Tensor
from torch.autograd.function import once_differentiable

from uw3dgs.kernels.build import extension
from uw3dgs.render.types import RasterSettings


class _Project(torch.autograd.Function):
    @staticmethod
    def forward(ctx, means, quats, scales, opacities, viewmat, K, width, height, settings):
        means2d, conics, depths, radii = extension().project_forward(
            means, quats, scales, opacities, viewmat, K, width, height,
            settings.near_plane, settings.far_plane, settings.eps2d, settings.alpha_min,
        )  # fmt: skip
        ctx.save_for_backward(means, quats, scales, viewmat, K)
        ctx.view = (width, height, settings)
        ctx.mark_non_differentiable(radii)
        return means2d, conics, depths, radii

    @staticmethod
    @once_differentiable
    def backward(ctx, g_means2d, g_conics, g_depths, _g_radii):
        means, quats, scales, viewmat, K = ctx.saved_tensors
        width, height, settings = ctx.view
        n = len(means)
        g_means2d = means.new_zeros(n, 2) if g_means2d is None else g_means2d.contiguous()
        g_conics = means.new_zeros(n, 3) if g_conics is None else g_conics.contiguous()
        g_depths = means.new_zeros(n) if g_depths is None else g_depths.contiguous()
        g_means, g_quats, g_scales = extension().project_backward(
            means, quats, scales, viewmat, K, width, height,
            settings.near_plane, settings.far_plane, settings.eps2d, g_means2d, g_conics, g_depths,
        )  # fmt: skip
        return g_means, g_quats, g_scales, None, None, None, None, None, None


def project(means: Tensor, quats: Tensor, scales: Tensor, opacities: Tensor, viewmat: Tensor, K: Tensor, width: int,
            height: int, settings: RasterSettings) -> tuple[Tensor, Tensor, Tensor, Tensor]:
    """(means2d [N, 2], conics [N, 3], depths [N], radii [N] int32) of contiguous CPU tensors of one float dtype:
    means [N, 3], quats [N, 4] (w, x, y, z), scales [N, 3], opacities [N] (read for the radii only, no gradient),
    viewmat [4, 4], K [3, 3]. Gradients flow from means2d, conics and depths to means, quats and scales."""
    return _Project.apply(means, quats, scales, opacities, viewmat, K, width, height, settings)
