"""The compiled CPU rasterizer ('cpu' backend): the projection and compositing stages of `uw3dgs/kernels/`.

It mirrors `reference.py` numerically: same projection, opacity-aware radii, (tile, depth) ordering, alpha_min /
alpha_max / early-termination rules and exp() floor, in float32 or float64. Two autograd functions keep `means2d` an
intermediate of the graph (so `retain_grad()` gives the screen-space gradient): projection (means, quats, scales ->
means2d, conics, depths) and compositing (means2d, conics, opacities, features + depth -> render, depth, alpha).
Where the kernels do not run (not a CPU float tensor, a tile larger than MAX_TILE, no build) it is the reference.
"""

from __future__ import annotations

import torch

from uw3dgs.cameras import Camera
from uw3dgs.kernels.compositing import Composite, rasterizes, reused
from uw3dgs.kernels.projection import project
from uw3dgs.render.reference import rasterize_reference
from uw3dgs.render.types import RasterOutput, RasterSettings, Splats, TileLists


def rasterize_cpu(splats: Splats, camera: Camera, settings: RasterSettings,
                  projection: RasterOutput | None = None) -> RasterOutput:
    """Same contract and numbers as `rasterize_reference`, compiled ('cpu' backend)."""
    if not rasterizes(splats.means, settings):
        return rasterize_reference(splats, camera, settings, projection)
    dtype = splats.means.dtype
    width, height = camera.width, camera.height
    opacities, features = (t.to(dtype).contiguous() for t in (splats.opacities, splats.features))
    tile_lists = None
    if projection is not None:
        means2d, conics, depths, radii, tile_lists = reused(projection, dtype, settings)
    else:
        means, quats, scales = (t.to(dtype).contiguous() for t in (splats.means, splats.quats, splats.scales))
        viewmat, K = (t.detach().to(dtype).contiguous() for t in (camera.viewmat, camera.K))
        # the projection reads the opacities for the radii only (no gradient): detached, a render whose Gaussians
        # are frozen but whose opacities carry one (PAUP's masked render) runs no projection backward
        means2d, conics, depths, radii = project(means, quats, scales, opacities.detach(), viewmat, K, width, height,
                                                 settings)
    feats = torch.cat([features, depths[:, None]], dim=1)  # depth composites like a feature
    # Separate render / depth / alpha outputs: no slicing, so no zero-fill + copy ops in the backward.
    render, depth, alpha, weight_sum, pixel_count, *lists = Composite.apply(
        means2d, conics, opacities, feats, depths.detach(), radii, width, height, settings, tile_lists
    )
    return RasterOutput(
        render=render,
        alpha=alpha,
        depth=depth,
        means2d=means2d,
        radii=radii,
        depths=depths,
        conics=conics,
        weight_sum=weight_sum,
        pixel_count=pixel_count,
        tile_lists=TileLists(settings.tile_size, tuple(lists)) if lists else None,
    )
