"""Pure-PyTorch medium compositor: the numerical reference of WaterSplatting's compositing, and its path wherever the
compiled one does not run (CUDA: gsplat has no such compositor).

A sibling of `reference.py`'s compositing: the same projection, binning, chunking, alpha and blending rules
(alpha_min, alpha_max, early termination), and the same alpha backward, with the water added per pixel. The medium
term telescopes (`MediumRasterOutput`): medium = c_med (1 - sum_i w_i exp(-sigma_bs z_i)), so both water terms are
weighted sums over the blended Gaussians like the colour, with per-(pixel, Gaussian) factors exp(-sigma z_i).
"""

from __future__ import annotations

import torch
from torch import Tensor
from torch.autograd.function import once_differentiable

from uw3dgs.cameras import Camera
from uw3dgs.render.medium_types import MediumRasterOutput, PixelMedium
from uw3dgs.render.projection import project_gaussians
from uw3dgs.render.reference import (
    _FEATS,
    _blend,
    _chunk_alpha,
    _geometry_grads,
    _image_to_tiles,
    _pack,
    _plan_chunks,
    _tiles_to_image,
    bin_gaussians,
)
from uw3dgs.render.types import RasterSettings, Splats

COLOR, DEPTH, ONE = slice(_FEATS, _FEATS + 3), _FEATS + 3, _FEATS + 4
"""Columns of the packed table: the Gaussians' RGB, their depth, the constant 1 (`reference._pack`)."""


def _water_factors(params: Tensor, medium: Tensor) -> tuple[Tensor, Tensor]:
    """exp(-sigma_attn z_i) and exp(-sigma_bs z_i), [nt, 3, P, K], for a chunk's packed rows [nt, K, ...] and its
    tiles' medium [nt, 9, P] (color, sigma_bs, sigma_attn)."""
    z = params[..., DEPTH][:, None, None, :]
    return torch.exp(-medium[:, 6:9, :, None] * z), torch.exp(-medium[:, 3:6, :, None] * z)


class _CompositeMediumTiles(torch.autograd.Function):
    """Outputs [H, W, 5] (restored RGB, depth, alpha), object [H, W, 3], medium [H, W, 3], weight_sum and
    pixel_count [N]; gradients to means2d, conics, opacities, colours and the [H, W, 9] medium (none to depths)."""

    @staticmethod
    def forward(ctx, means2d, conics, opacities, colors, depths, medium, bins, width, height, settings, absgrad):
        n = len(means2d)
        table = _pack(means2d, conics, opacities, torch.cat([colors, depths[:, None]], dim=1))
        chunks = _plan_chunks(bins, n, width, height, settings.alpha_min, table.dtype)
        n_tiles = bins.tiles_x * bins.tiles_y
        medium_tiles = _image_to_tiles(medium, bins)  # [tiles, 9, P]
        out = table.new_zeros(n_tiles, table.shape[1] - _FEATS, bins.tile_size**2)
        obj = table.new_zeros(n_tiles, 3, bins.tile_size**2)
        water = medium_tiles[:, 0:3].clone()  # where no Gaussian is blended: c_med
        weight_sum = table.new_zeros(n + 1)
        pixel_count = torch.zeros(n + 1, dtype=torch.int32, device=table.device)
        for chunk in chunks:
            ca = _chunk_alpha(chunk, table, settings.alpha_max)
            blend = _blend(ca.alpha, settings.transmittance_min)
            weights = blend.weights.flatten(1, 2)  # [nt, P, K]
            out[chunk.tiles] = torch.bmm(ca.params[..., _FEATS:].transpose(1, 2), weights.transpose(1, 2))
            med = medium_tiles[chunk.tiles]
            attenuated, scattered = _water_factors(ca.params, med)
            colors_ck = ca.params[..., COLOR].transpose(1, 2)[:, :, None, :]  # [nt, 3, 1, K]
            obj[chunk.tiles] = (attenuated * colors_ck * weights[:, None]).sum(-1)
            water[chunk.tiles] = med[:, 0:3] * (1.0 - (scattered * weights[:, None]).sum(-1))
            flat_ids = chunk.gids.flatten()
            weight_sum.index_add_(0, flat_ids, weights.sum(1).flatten())
            blended = ca.hit.mul_(blend.kept).sum((1, 2)).to(torch.int32)
            pixel_count.index_add_(0, flat_ids, blended.flatten())

        ctx.save_for_backward(table, medium_tiles)
        ctx.plan = (bins, chunks, settings, width, height, absgrad)
        weight_sum, pixel_count = weight_sum[:n], pixel_count[:n]
        ctx.mark_non_differentiable(weight_sum, pixel_count)
        images = (_tiles_to_image(t, bins, width, height) for t in (out, obj, water))
        return *images, weight_sum, pixel_count

    @staticmethod
    @once_differentiable
    def backward(ctx, grad_out, grad_obj, grad_water, _grad_weight_sum, _grad_pixel_count):
        bins, chunks, settings, width, height, absgrad = ctx.plan
        table, medium_tiles = ctx.saved_tensors
        grad_out, grad_obj, grad_water = (_image_to_tiles(g, bins) for g in (grad_out, grad_obj, grad_water))
        grads = torch.zeros_like(table)
        grad_medium = torch.zeros_like(medium_tiles)
        grad_medium[:, 0:3] = grad_water  # d medium / d c_med = 1 where nothing is blended
        abs_sums = table.new_zeros(len(table), 2) if absgrad is not None else None
        for chunk in chunks:
            ca = _chunk_alpha(chunk, table, settings.alpha_max)
            blend = _blend(ca.alpha, settings.transmittance_min)
            weights = blend.weights.flatten(1, 2)  # [nt, P, K]
            med, g_out, g_obj, g_water = (t[chunk.tiles] for t in (medium_tiles, grad_out, grad_obj, grad_water))
            attenuated, scattered = _water_factors(ca.params, med)
            colors = ca.params[..., COLOR]  # [nt, K, 3]
            g_scattered = g_water * med[:, 0:3]  # dL/d(sum_i w_i exp(-sigma_bs z_i)) = -this
            # dL/dw_i per pixel: the restored image, depth and alpha as 3DGS, plus the two water terms
            g_weights = torch.bmm(g_out.transpose(1, 2), ca.params[..., _FEATS:].transpose(1, 2))
            g_weights += torch.einsum("ncp,nkc,ncpk->npk", g_obj, colors, attenuated)
            g_weights -= torch.einsum("ncp,ncpk->npk", g_scattered, scattered)
            weighted = (g_weights * weights).view_as(ca.alpha)
            chunk_abs = ca.params.new_zeros(*chunk.gids.shape, 2) if abs_sums is not None else None
            geometry = _geometry_grads(ca, blend, weighted, settings, chunk_abs)

            w_attenuated = attenuated * weights[:, None]  # [nt, 3, P, K]
            grad_colors = torch.bmm(g_out[:, 0:3], weights).transpose(1, 2)
            grad_colors += torch.einsum("ncp,ncpk->nkc", g_obj, w_attenuated)
            z = ca.params[..., DEPTH][:, None, None, :]
            w_scattered = scattered * weights[:, None]
            g_med = torch.cat([
                g_water * (1.0 - w_scattered.sum(-1)),
                g_scattered * (w_scattered * z).sum(-1),
                -g_obj * (w_attenuated * z * colors.transpose(1, 2)[:, :, None, :]).sum(-1),
            ], dim=1)
            grad_medium[chunk.tiles] = g_med
            rows = torch.cat([geometry, grad_colors], dim=-1)
            grads[:, : rows.shape[-1]].index_add_(0, chunk.gids.flatten(), rows.flatten(0, 1))
            if abs_sums is not None:
                abs_sums.index_add_(0, chunk.gids.flatten(), chunk_abs.flatten(0, 1))
        if absgrad is not None:
            absgrad += abs_sums[:-1].to(absgrad.dtype)
        grads = grads[:-1]
        grad_medium_image = _tiles_to_image(grad_medium, bins, width, height)
        return (grads[:, :2], grads[:, 2:5], grads[:, 5], grads[:, COLOR], None, grad_medium_image,
                *[None] * 5)


def rasterize_medium_reference(splats: Splats, medium: PixelMedium, camera: Camera, settings: RasterSettings,
                               absgrad: bool = False) -> MediumRasterOutput:
    """Render `splats.features` (colours [N, 3]) into one view of `camera` with the water composited between the
    Gaussians ('torch' backend).

    Splats are activated as for `rasterize_reference`; `medium` holds [H, W, 3] per-pixel water parameters. Returns
    the restored image as `render`, `object` and `medium` (see `MediumRasterOutput`), alpha and depth = sum_i w_i z_i
    (no gradient to z). `absgrad`: also fill `absgrad` [N, 2] in the backward.
    """
    width, height = camera.width, camera.height
    medium.check(width, height)
    proj = project_gaussians(splats.means, splats.quats, splats.scales, splats.opacities, camera.viewmat, camera.K,
                             width, height, settings)
    bins = bin_gaussians(proj, width, height, settings.tile_size)
    abs_buffer = splats.means.new_zeros(len(splats.means), 2) if absgrad else None
    restored, obj, water, weight_sum, pixel_count = _CompositeMediumTiles.apply(
        proj.means2d, proj.conics, splats.opacities, splats.features, proj.depths.detach(), medium.packed(), bins,
        width, height, settings, abs_buffer,
    )
    return MediumRasterOutput(
        render=restored[..., 0:3],
        alpha=restored[..., 4],
        depth=restored[..., 3],
        means2d=proj.means2d,
        radii=proj.radii,
        depths=proj.depths,
        conics=proj.conics,
        weight_sum=weight_sum,
        pixel_count=pixel_count,
        object=obj,
        medium=water,
        absgrad=abs_buffer,
    )
