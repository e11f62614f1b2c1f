"""The compositing stage (`compositing.h`, `compositing.cpp`): binning and alpha blending of projected Gaussians over
any number of feature channels, its hand-written backward, and PAUP's masked render with its L1 in one pass.

Gradients are accumulated per (tile, Gaussian) slot and reduced per Gaussian in a fixed order, so results are
bitwise reproducible whatever the thread count. When a gradient is needed, the forward also records which pixels
each Gaussian blended (4 bytes per blended run of 8 or 16 pixels), and the backward replays exactly those; under
`torch.no_grad()` nothing is recorded.
"""

from __future__ import annotations

import torch
from torch import Tensor
from torch.autograd.function import once_differentiable

from uw3dgs.kernels.build import extension, runs_on
from uw3dgs.render.types import RasterOutput, RasterSettings

MAX_TILE = 256
"""Largest tile_size the compiled compositing takes (its per-row codes hold 8-bit rows); larger ones use the
reference."""


def rasterizes(tensor: Tensor, settings: RasterSettings) -> bool:
    """Whether the compiled rasterizer takes Gaussians of this tensor's device and dtype with these settings."""
    return settings.tile_size <= MAX_TILE and runs_on(tensor)


def reused(projection: RasterOutput, dtype: torch.dtype, settings: RasterSettings) -> tuple[Tensor, ...]:
    """An earlier render's screen-space Gaussians (means2d, conics, depths in `dtype`, radii) and its tile lists when
    made with these settings (None: bin again; the same outputs either way, composite_forward)."""
    means2d, conics, depths = (t.detach().to(dtype).contiguous()
                               for t in (projection.means2d, projection.conics, projection.depths))
    lists = projection.tile_lists
    lists = lists.tensors if lists is not None and lists.tile_size == settings.tile_size else None
    return means2d, conics, depths, projection.radii.contiguous(), lists


class Composite(torch.autograd.Function):
    @staticmethod
    def forward(ctx, means2d, conics, opacities, feats, depths, radii, width, height, settings, tile_lists):
        ext = extension()
        for_backward = any(ctx.needs_input_grad[:4])  # else no state is recorded for a backward
        render, depth, alpha, weight_sum, pixel_count, *state = ext.composite_forward(
            means2d, conics, opacities, feats, depths, radii, width, height, settings.tile_size,
            settings.alpha_min, settings.alpha_max, settings.transmittance_min, for_backward, list(tile_lists or ()),
        )  # fmt: skip
        ctx.save_for_backward(means2d, conics, opacities, feats, *state)
        ctx.view = (width, height, settings)
        # the state's tile lists (tile starts, sorted Gaussians, their slots, Gaussian starts), for a later render
        lists = state[1:5] if for_backward else []
        ctx.mark_non_differentiable(weight_sum, pixel_count, *lists)
        return render, depth, alpha, weight_sum, pixel_count, *lists

    @staticmethod
    @once_differentiable
    def backward(ctx, grad_render, grad_depth, grad_alpha, _grad_weight_sum, _grad_pixel_count, *_grad_lists):
        means2d, conics, opacities, feats, *state = ctx.saved_tensors
        width, height, settings = ctx.view
        empty = means2d.new_empty(0)  # stands for a zero gradient: unused outputs cost nothing
        # frozen Gaussians (PAUP's masked render) need the opacities' gradient only: about half the work
        geometry = any(ctx.needs_input_grad[i] for i in (0, 1, 3))
        g_means2d, g_conics, g_opacities, g_feats = extension().composite_backward(
            means2d, conics, opacities, feats, width, height, settings.tile_size,
            settings.alpha_max, state,
            *(empty if g is None else g.contiguous() for g in (grad_render, grad_depth, grad_alpha)), geometry,
        )  # fmt: skip
        if not geometry:
            g_means2d = g_conics = g_feats = None
        return g_means2d, g_conics, g_opacities, g_feats, None, None, None, None, None, None


class _MaskedL1(torch.autograd.Function):
    """PAUP's masked render and its L1 to a target in one compiled pass (masked_l1): the forward already has the
    opacities' gradient, so the backward only scales it."""

    @staticmethod
    def forward(ctx, opacities, means2d, conics, features, depths, radii, target, width, height, settings, tile_lists):
        image, l1, grad = extension().masked_l1(
            means2d, conics, opacities, features, depths, radii, width, height, settings.tile_size,
            settings.alpha_min, settings.alpha_max, settings.transmittance_min, list(tile_lists or ()), target,
        )  # fmt: skip
        ctx.save_for_backward(grad)
        ctx.mark_non_differentiable(image)
        return image, l1

    @staticmethod
    @once_differentiable
    def backward(ctx, _grad_image, grad_l1):
        (grad,) = ctx.saved_tensors
        return grad * grad_l1, None, None, None, None, None, None, None, None, None, None


def masked_l1(projection: RasterOutput, opacities: Tensor, features: Tensor, target: Tensor, width: int,
                  height: int, settings: RasterSettings) -> tuple[Tensor, Tensor] | None:
    """`uw3dgs.render.masked_l1` on the compiled kernels; None where it does not run (not a CPU float tensor, a tile
    larger than MAX_TILE, no build)."""
    if not rasterizes(opacities, settings):
        return None
    dtype = opacities.dtype
    means2d, conics, depths, radii, lists = reused(projection, dtype, settings)
    return _MaskedL1.apply(opacities.contiguous(), means2d, conics, features.detach().to(dtype).contiguous(), depths,
                           radii, target.detach().to(dtype).contiguous(), width, height, settings, lists)
