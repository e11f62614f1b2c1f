"""WaterSplatting's medium compositor, compiled (`medium_compositing.cpp`): the same numbers as
`uw3dgs/render/medium_reference.py` (float rounding aside) with a hand-written C++ backward; a sibling of
`compositing.py` that shares the compiled projection (`projection.py`, so `means2d` stays in the graph), the
compiled binning and the SIMD tile structs of the 3DGS compositing, and adds the water through their hook.
"""

from __future__ import annotations

import torch
from torch import Tensor
from torch.autograd.function import once_differentiable

from uw3dgs.cameras import Camera
from uw3dgs.kernels.build import extension, runs_on
from uw3dgs.kernels.compositing import MAX_TILE
from uw3dgs.kernels.projection import project
from uw3dgs.render.medium_types import MediumRasterOutput, PixelMedium
from uw3dgs.render.types import RasterSettings, Splats


def takes(means: Tensor, settings: RasterSettings) -> bool:
    """Whether the compiled medium compositor runs for Gaussians of this tensor's device and dtype."""
    return runs_on(means) and settings.tile_size <= MAX_TILE


class _CompositeMedium(torch.autograd.Function):
    """Outputs restored [H, W, 3], depth, alpha [H, W], object, water [H, W, 3], weight_sum and pixel_count [N];
    gradients to means2d, conics, opacities, colours and the [H, W, 9] medium (none to depths)."""

    @staticmethod
    def forward(ctx, means2d, conics, opacities, colors, depths, radii, medium, width, height, settings, absgrad):
        feats = torch.cat([colors, depths[:, None]], dim=1)  # the depth image composites like a colour
        for_backward = any(ctx.needs_input_grad[:4]) or ctx.needs_input_grad[6]  # else no trace is recorded
        restored, depth, alpha, obj, water, weight_sum, pixel_count, *state = extension().medium_composite_forward(
            means2d, conics, opacities, feats, depths, radii, medium, width, height, settings.tile_size,
            settings.alpha_min, settings.alpha_max, settings.transmittance_min, for_backward)
        ctx.save_for_backward(means2d, conics, opacities, feats, medium, *state)
        ctx.view = (width, height, settings.tile_size, settings.alpha_max)
        ctx.absgrad = absgrad
        ctx.mark_non_differentiable(weight_sum, pixel_count)
        return restored, depth, alpha, obj, water, weight_sum, pixel_count

    @staticmethod
    @once_differentiable
    def backward(ctx, g_restored, g_depth, g_alpha, g_obj, g_water, _g_weight_sum, _g_pixel_count):
        means2d, conics, opacities, feats, medium, *state = ctx.saved_tensors
        height, width = medium.shape[:2]
        grads = [torch.zeros(shape, dtype=means2d.dtype) if g is None else g.contiguous()
                 for g, shape in ((g_restored, (height, width, 3)), (g_depth, (height, width)),
                                  (g_alpha, (height, width)), (g_obj, (height, width, 3)),
                                  (g_water, (height, width, 3)))]
        g_means2d, g_conics, g_opacities, g_colors, g_medium, abs_sums = extension().medium_composite_backward(
            means2d, conics, opacities, feats, medium, *ctx.view, state, *grads)
        if ctx.absgrad is not None:
            ctx.absgrad += abs_sums
        return g_means2d, g_conics, g_opacities, g_colors, None, None, g_medium, *[None] * 4


def rasterize_medium_cpu(splats: Splats, medium: PixelMedium, camera: Camera, settings: RasterSettings,
                         absgrad: bool = False) -> MediumRasterOutput:
    """`rasterize_medium_reference`'s contract and numbers, compiled (callers check `takes` first)."""
    width, height = camera.width, camera.height
    medium.check(width, height)
    dtype = splats.means.dtype
    means, quats, scales = (t.to(dtype).contiguous() for t in (splats.means, splats.quats, splats.scales))
    opacities, colors = (t.to(dtype).contiguous() for t in (splats.opacities, splats.features))
    viewmat, K = (t.detach().to(dtype).contiguous() for t in (camera.viewmat, camera.K))
    means2d, conics, depths, radii = project(means, quats, scales, opacities.detach(), viewmat, K, width, height,
                                             settings)
    abs_buffer = means.new_zeros(len(means), 2) if absgrad else None
    restored, depth, alpha, obj, water, weight_sum, pixel_count = _CompositeMedium.apply(
        means2d, conics, opacities, colors, depths.detach(), radii, medium.packed().to(dtype).contiguous(), width,
        height, settings, abs_buffer)
    return MediumRasterOutput(render=restored, alpha=alpha, depth=depth, means2d=means2d, radii=radii, depths=depths,
                              conics=conics, weight_sum=weight_sum, pixel_count=pixel_count, object=obj,
                              medium=water, absgrad=abs_buffer)
