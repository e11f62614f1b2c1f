"""Pure-PyTorch tile-based 3DGS rasterizer: the numerical reference for every other backend.

Same algorithm as the 3DGS CUDA rasterizer, vectorised: Gaussians are binned into the screen tiles
their bounding square covers, each tile's list is sorted front to back, and tiles are composited in
chunks of padded [tiles, Gaussians, pixels] tensors. Compositing is a custom autograd function whose
backward recomputes each chunk instead of storing it, so memory stays bounded by the chunk size
however many Gaussians and pixels there are.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import torch
from torch import Tensor
from torch.autograd.function import once_differentiable

from uw3dgs.cameras import Camera
from uw3dgs.render.projection import Projection, screen_gaussians
from uw3dgs.render.types import RasterOutput, RasterSettings, Splats

CHUNK_ELEMENTS = 1 << 20
"""Tiles x Gaussians-per-tile x pixels-per-tile per vectorised step: ~4 MB per float32 temporary."""
EXP_FLOOR = -80.0
"""exp() arguments are clamped here: far below any alpha_min, and exp stays a normal float32."""


@dataclass
class TileBins:
    """Gaussians binned into screen tiles, each tile's list sorted front to back."""

    gauss_ids: Tensor
    """[pairs] Gaussian index of every (tile, Gaussian) pair, sorted by tile then depth."""
    tile_starts: Tensor
    """[tiles] offset of each tile's list in gauss_ids."""
    tile_counts: Tensor
    """[tiles] length of each tile's list."""
    tiles_x: int
    tiles_y: int
    tile_size: int


@dataclass
class _Chunk:
    """A group of tiles composited in one vectorised step."""

    tiles: Tensor
    """[nt] tile indices (row-major over the tile grid)."""
    gids: Tensor
    """[nt, K] front-to-back Gaussian indices; padding points at the zero-opacity dummy row N."""
    px: Tensor
    """[nt, T] pixel-centre x of the tiles' columns."""
    py: Tensor
    """[nt, T] pixel-centre y of the tiles' rows."""
    threshold: Tensor
    """[nt, T, T, 1] alpha_min per pixel, infinite where the tile sticks out of the image."""


def _pixel_span(centre: Tensor, radius: Tensor, size: int) -> tuple[Tensor, Tensor]:
    """First and last pixel index whose centre (index + 0.5) lies within radius of centre."""
    first = torch.ceil(centre - radius - 0.5).clamp(0, size - 1).long()
    last = torch.floor(centre + radius - 0.5).clamp(0, size - 1).long()
    return first, last


def bin_gaussians(proj: Projection, width: int, height: int, tile_size: int) -> TileBins:
    """Copy each visible Gaussian into every tile its bounding square touches, sorted by (tile, depth)."""
    device = proj.means2d.device
    tiles_x = -(-width // tile_size)
    tiles_y = -(-height // tile_size)
    ids = proj.valid.nonzero().squeeze(1)
    ids = ids[torch.argsort(proj.depths.detach()[ids], stable=True)]
    centres = proj.means2d.detach()[ids]
    radius = proj.radii[ids].to(centres.dtype)
    x0, x1 = (p // tile_size for p in _pixel_span(centres[:, 0], radius, width))
    y0, y1 = (p // tile_size for p in _pixel_span(centres[:, 1], radius, height))
    span_x = x1 - x0 + 1
    counts = span_x * (y1 - y0 + 1)

    owner = torch.repeat_interleave(torch.arange(len(ids), device=device), counts)
    local = torch.arange(len(owner), device=device) - (torch.cumsum(counts, 0) - counts)[owner]
    tile = (y0[owner] + local // span_x[owner]) * tiles_x + x0[owner] + local % span_x[owner]
    tile_sorted, order = torch.sort(tile, stable=True)
    tile_counts = torch.bincount(tile_sorted, minlength=tiles_x * tiles_y)
    return TileBins(
        gauss_ids=ids[owner[order]],
        tile_starts=torch.cumsum(tile_counts, 0) - tile_counts,
        tile_counts=tile_counts,
        tiles_x=tiles_x,
        tiles_y=tiles_y,
        tile_size=tile_size,
    )


def _plan_chunks(
    bins: TileBins, pad_id: int, width: int, height: int, alpha_min: float, dtype: torch.dtype
) -> list[_Chunk]:
    """Group non-empty tiles by decreasing list length: little padding, each chunk within CHUNK_ELEMENTS."""
    pixels = bins.tile_size**2
    px, py, threshold = _tile_pixels(bins, width, height, alpha_min, dtype)
    counts, order = torch.sort(bins.tile_counts, descending=True)
    n_nonempty = int((counts > 0).sum())
    counts_list = counts[:n_nonempty].tolist()
    chunks = []
    start = 0
    while start < n_nonempty:
        k = counts_list[start]
        stop = min(n_nonempty, start + max(1, CHUNK_ELEMENTS // (k * pixels)))
        tiles = order[start:stop]
        slot = torch.arange(k, device=tiles.device)
        idx = bins.tile_starts[tiles, None] + slot
        padding = slot >= bins.tile_counts[tiles, None]
        gids = bins.gauss_ids[idx.clamp(max=len(bins.gauss_ids) - 1)].masked_fill(padding, pad_id)
        chunks.append(_Chunk(tiles, gids, px[tiles], py[tiles], threshold[tiles]))
        start = stop
    return chunks


def _tile_pixels(
    bins: TileBins, width: int, height: int, alpha_min: float, dtype: torch.dtype
) -> tuple[Tensor, Tensor, Tensor]:
    """Per tile: column centres x [tiles, T], row centres y [tiles, T], alpha_min per pixel [tiles, T, T, 1]."""
    device = bins.gauss_ids.device
    offsets = torch.arange(bins.tile_size, device=device)
    x = (torch.arange(bins.tiles_x, device=device)[:, None] * bins.tile_size + offsets).repeat(bins.tiles_y, 1)
    y = (torch.arange(bins.tiles_y, device=device)[:, None] * bins.tile_size + offsets).repeat_interleave(
        bins.tiles_x, dim=0
    )
    inside = (y < height)[:, :, None] & (x < width)[:, None, :]
    threshold = torch.where(inside, alpha_min, torch.inf).to(dtype)[..., None]
    return x.to(dtype) + 0.5, y.to(dtype) + 0.5, threshold


def _pack(means2d: Tensor, conics: Tensor, opacities: Tensor, feats: Tensor) -> Tensor:
    """[N+1, 7+F] rows (mean x, mean y, conic a, b, c, opacity, feats..., 1) so a chunk needs one gather.

    The trailing 1 composites to alpha; the appended zero row (zero opacity) is what padding slots hit.
    """
    ones = feats.new_ones((len(feats), 1))
    table = torch.cat([means2d, conics, opacities[:, None], feats, ones], dim=1)
    return torch.cat([table, table.new_zeros((1, table.shape[1]))])


_FEATS = 6
"""Column of the packed table where the composited channels start."""


@dataclass
class _ChunkAlpha:
    """A chunk's alphas after the alpha_min and power rules, Gaussians along the last dim."""

    alpha: Tensor
    """[nt, T, T, K] alpha per (tile, row, column, Gaussian); 0 where skipped."""
    hit: Tensor
    """[nt, T, T, K] 1 where not skipped (power <= 0, alpha >= alpha_min, pixel in the image), else 0."""
    dx: Tensor
    """[nt, T, K] pixel-centre x minus mean x per column."""
    dy: Tensor
    """[nt, T, K] pixel-centre y minus mean y per row."""
    params: Tensor
    """[nt, K, 7+F] the Gaussians' packed rows."""


def _chunk_alpha(chunk: _Chunk, table: Tensor, alpha_max: float) -> _ChunkAlpha:
    """Evaluate every padded (tile, Gaussian) pair at every pixel of its tile."""
    params = table[chunk.gids]
    dx = chunk.px[:, :, None] - params[:, None, :, 0]
    dy = chunk.py[:, :, None] - params[:, None, :, 1]
    a, b, c, opacity = (params[:, None, :, i] for i in range(2, 6))
    log_opacity = torch.log(opacity)  # folded into the exponent: saves a full-size multiply
    # log(opacity) + power[y, x], power = -a dx^2/2 - c dy^2/2 - b dx dy, from separable row / column terms.
    exponent = (-0.5 * c * dy * dy + log_opacity)[:, :, None] + (-0.5 * a * dx * dx)[:, None]
    exponent.addcmul_((-b * dy)[:, :, None], dx[:, None])
    alpha = exponent.clamp(min=EXP_FLOOR).exp_().clamp_(max=alpha_max)
    hit = _float_mask(torch.le, exponent, log_opacity[:, None], out=exponent)  # power <= 0
    hit.mul_(_float_mask(torch.ge, alpha, chunk.threshold))
    return _ChunkAlpha(alpha=alpha.mul_(hit), hit=hit, dx=dx, dy=dy, params=params)


def _float_mask(compare: Callable[..., Tensor], x: Tensor, y: Tensor, out: Tensor | None = None) -> Tensor:
    """compare(x, y) as 0/1 in x's dtype: on CPU, comparisons writing floats vectorise, bool ones do not."""
    return compare(x, y, out=torch.empty_like(x) if out is None else out)


@dataclass
class _Blend:
    """Front-to-back compositing of a chunk, Gaussians along the last dim."""

    weights: Tensor
    """alpha_i T_i, 0 where not blended."""
    transmit: Tensor
    """1 - alpha_i."""
    kept: Tensor
    """1 before early termination (the transmittance after i is still >= transmittance_min), else 0."""


def _blend(alpha: Tensor, transmittance_min: float) -> _Blend:
    """Blending weights with 3DGS early termination.

    A Gaussian is blended only if the transmittance after it stays >= transmittance_min; since that
    transmittance never increases, this also drops everything behind the first one that fails.
    """
    transmit = 1.0 - alpha
    t_after = torch.cumprod(transmit, dim=-1)
    weights = torch.empty_like(alpha)
    weights[..., 0] = alpha[..., 0]
    torch.mul(alpha[..., 1:], t_after[..., :-1], out=weights[..., 1:])
    kept = _float_mask(torch.ge, t_after, transmittance_min, out=t_after)
    return _Blend(weights=weights.mul_(kept), transmit=transmit, kept=kept)


# Per-tile pixel buffers are channel-major, [tiles, C, T*T]: MKL's skinny batched GEMMs are several
# times faster with the few channels as the rows of the output than as its columns.


def _tiles_to_image(tiles: Tensor, bins: TileBins, width: int, height: int) -> Tensor:
    """[tiles, C, T*T] per-tile pixels to a [height, width, C] image."""
    t = bins.tile_size
    grid = tiles.view(bins.tiles_y, bins.tiles_x, -1, t, t).permute(0, 3, 1, 4, 2)
    return grid.reshape(bins.tiles_y * t, bins.tiles_x * t, -1)[:height, :width]


def _image_to_tiles(image: Tensor, bins: TileBins) -> Tensor:
    """[height, width, C] image to [tiles, C, T*T] per-tile pixels, zero-padded at the border."""
    t = bins.tile_size
    height, width, channels = image.shape
    padded = image.new_zeros(bins.tiles_y * t, bins.tiles_x * t, channels)
    padded[:height, :width] = image
    grid = padded.view(bins.tiles_y, t, bins.tiles_x, t, channels).permute(0, 2, 4, 1, 3)
    return grid.reshape(bins.tiles_y * bins.tiles_x, channels, t * t)


class _CompositeTiles(torch.autograd.Function):
    """Alpha-composites binned Gaussians; outputs a [H, W, F+1] image (feats, then alpha)."""

    @staticmethod
    def forward(ctx, means2d, conics, opacities, feats, bins, width, height, settings):
        n = len(means2d)
        table = _pack(means2d, conics, opacities, feats)
        chunks = _plan_chunks(bins, n, width, height, settings.alpha_min, table.dtype)
        out = table.new_zeros(bins.tiles_x * bins.tiles_y, table.shape[1] - _FEATS, bins.tile_size**2)
        weight_sum = table.new_zeros(n + 1)
        pixel_count = torch.zeros(n + 1, dtype=torch.int32, device=table.device)
        for chunk in chunks:
            ca = _chunk_alpha(chunk, table, settings.alpha_max)
            blend = _blend(ca.alpha, settings.transmittance_min)
            weights = blend.weights.flatten(1, 2)  # [nt, P, K]
            out[chunk.tiles] = torch.bmm(ca.params[..., _FEATS:].transpose(1, 2), weights.transpose(1, 2))
            flat_ids = chunk.gids.flatten()
            weight_sum.index_add_(0, flat_ids, weights.sum(1).flatten())
            blended = ca.hit.mul_(blend.kept).sum((1, 2)).to(torch.int32)
            pixel_count.index_add_(0, flat_ids, blended.flatten())

        ctx.save_for_backward(table)
        ctx.plan = (bins, chunks, settings, feats.shape[1])
        weight_sum, pixel_count = weight_sum[:n], pixel_count[:n]
        ctx.mark_non_differentiable(weight_sum, pixel_count)
        return _tiles_to_image(out, bins, width, height), weight_sum, pixel_count

    @staticmethod
    @once_differentiable
    def backward(ctx, grad_image, _grad_weight_sum, _grad_pixel_count):
        bins, chunks, settings, n_feats = ctx.plan
        (table,) = ctx.saved_tensors
        grad_tiles = _image_to_tiles(grad_image, bins)
        grads = torch.zeros_like(table)
        for chunk in chunks:
            ca = _chunk_alpha(chunk, table, settings.alpha_max)
            rows = _chunk_grads(ca, grad_tiles[chunk.tiles], settings)
            grads.index_add_(0, chunk.gids.flatten(), rows.flatten(0, 1))
        grads = grads[:-1]
        return grads[:, :2], grads[:, 2:5], grads[:, 5], grads[:, _FEATS : _FEATS + n_feats], *[None] * 4


def _chunk_grads(ca: _ChunkAlpha, grad_out: Tensor, settings: RasterSettings) -> Tensor:
    """[nt, K, 7+F] gradients of a chunk's packed rows given [nt, F+1, P] output gradients.

    The 3DGS backward, vectorised. With w_i = alpha_i T_i and g_i = dL/dout . f_i per pixel:
    dL/dalpha_i = T_i g_i - S_i / (1 - alpha_i) with S_i = sum_{j > i} w_j g_j, and
    alpha_i = opacity_i exp(power_i) gives dL/dpower_i = alpha_i dL/dalpha_i (0 where clamped).
    """
    blend = _blend(ca.alpha, settings.transmittance_min)
    weights = blend.weights
    feats = ca.params[..., _FEATS:]
    grad_feats = torch.bmm(grad_out, weights.flatten(1, 2)).transpose(1, 2)

    weighted = torch.bmm(grad_out.transpose(1, 2), feats.transpose(1, 2)).view_as(ca.alpha)
    weighted.mul_(weights)  # w_i g_i
    return torch.cat([_geometry_grads(ca, blend, weighted, settings), grad_feats], dim=-1)


def _geometry_grads(ca: _ChunkAlpha, blend: _Blend, weighted: Tensor, settings: RasterSettings,
                    absgrad: Tensor | None = None) -> Tensor:
    """[nt, K, 6] gradients of the packed rows' means2d, conic and opacity columns given `weighted` [nt, T, T, K] =
    w_i g_i, g_i = dL/dw_i per pixel (consumed). `absgrad` [nt, K, 2], if given, receives the sum over pixels of
    the per-pixel gradient's absolute value with respect to the mean (x, y)."""
    alpha, dx, dy, params = ca.alpha, ca.dx, ca.dy, ca.params
    behind = torch.cumsum(weighted, dim=-1)
    behind = behind[..., -1:] - behind  # S_i
    grad_power = torch.addcdiv(weighted, behind.mul_(alpha), blend.transmit, value=-1.0)
    grad_power.mul_(_float_mask(torch.lt, alpha, settings.alpha_max))
    a, b, c, opacity = params[..., 2:6].unbind(-1)
    if absgrad is not None:  # per pixel: dL/dmean = dL/dpower (a dx + b dy, b dx + c dy)
        for axis, (u, v) in enumerate(((a, b), (b, c))):
            per_pixel = (u[:, None, None] * dx[:, None] + v[:, None, None] * dy[:, :, None]).mul_(grad_power)
            absgrad[..., axis] = per_pixel.abs_().sum((1, 2))

    # Moments of dL/dpower over the tile's pixels, via separable row / column sums.
    per_col = grad_power.sum(1)  # [nt, T, K], summed over rows
    per_row = grad_power.sum(2)  # [nt, T, K], summed over columns
    row_dx = grad_power.mul_(dx[:, None]).sum(2)  # sum_x G[y, x] dx[x]
    s_dx = (per_col * dx).sum(1)
    s_dy = (per_row * dy).sum(1)
    s_dx2 = (per_col * dx * dx).sum(1)
    s_dy2 = (per_row * dy * dy).sum(1)
    s_dxdy = (row_dx * dy).sum(1)

    grad_opacity = per_col.sum(1) / opacity.clamp_min(torch.finfo(opacity.dtype).tiny)
    columns = (a * s_dx + b * s_dy, b * s_dx + c * s_dy, -0.5 * s_dx2, -s_dxdy, -0.5 * s_dy2, grad_opacity)
    return torch.stack(columns, dim=-1)


def rasterize_reference(splats: Splats, camera: Camera, settings: RasterSettings,
                        projection: RasterOutput | None = None) -> RasterOutput:
    """Render `splats.features` [N, C] into one view of `camera` ('torch' backend).

    The splats are activated: scales exp'd, opacities sigmoid'd, quats (w, x, y, z) any norm.
    Outputs are a [H, W, C] render and [H, W] alpha and depth, not composed over any background
    (callers add (1 - alpha[..., None]) * background). `projection`: see `uw3dgs.render.rasterize`.
    """
    opacities, features, width, height = splats.opacities, splats.features, camera.width, camera.height
    proj = screen_gaussians(splats, camera, settings, projection)
    bins = bin_gaussians(proj, width, height, settings.tile_size)
    feats = torch.cat([features, proj.depths[:, None]], dim=1)  # depth composites like a feature
    image, weight_sum, pixel_count = _CompositeTiles.apply(
        proj.means2d, proj.conics, opacities, feats, bins, width, height, settings
    )
    channels = features.shape[1]
    return RasterOutput(
        render=image[..., :channels],
        alpha=image[..., channels + 1],
        depth=image[..., channels],
        means2d=proj.means2d,
        radii=proj.radii,
        depths=proj.depths,
        conics=proj.conics,
        weight_sum=weight_sum,
        pixel_count=pixel_count,
    )
