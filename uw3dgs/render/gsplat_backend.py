"""gsplat CUDA rasterizer ('gsplat' backend, optional extra: ``pip install uw3dgs[cuda]``).

Same contract and numbers as `rasterize_reference`: the same render, alpha, depth, means2d, radii, depths,
per-Gaussian blending-weight sums and touched-pixel counts. gsplat 1.5.3 (a pure-Python wheel that JIT-compiles
its CUDA kernels on first use, which needs the CUDA toolkit, nvcc) provides the heavy kernels; this module keeps
every convention of the reference under its own control.

What comes from where
---------------------
- **Projection**: our own `project_gaussians` (the reference's PyTorch code, autograd, a few elementwise ops per
  Gaussian), not gsplat's `fully_fused_projection`. gsplat 1.5.3's projection differs from the reference in ways
  that change the outputs: (1) its Jacobian clamp is asymmetric around the principal point
  (``x/z`` in ``[-(cx/fx + 0.15 W/fx), (W - cx)/fx + 0.15 W/fx]``), ours is ``+-0.65 W/fx`` around the optical
  axis, the same only when ``cx == W/2`` (and likewise for y), which real COLMAP cameras never have exactly;
  (2) it returns per-axis radii ``[N, 2]`` of a box with a 3.33-sigma cap and culls on ``box vs [0, W]``, we
  return the reference's square radius ``[N]`` culled on pixel centres; (3) for culled Gaussians it does not
  write ``means2d``, ``depths`` and ``conics`` (``torch.empty`` memory), whereas `RasterOutput` has them for every
  Gaussian;
  (4) float32 only. Its camera conventions are otherwise ours: world-to-camera ``viewmat`` (row-major, applied as
  ``R p + t``), ``K`` in pixels with pixel centres at ``+0.5``, quaternions ``(w, x, y, z)`` normalised inside,
  ``eps2d`` added to the 2D covariance diagonal, culling at ``z < near_plane`` / ``z > far_plane``
  (tests/test_gsplat_backend.py checks this against gsplat's PyTorch projection).
- **Tile binning**: gsplat's ``isect_tiles`` (with our radii, as ``(r, r)``) and ``isect_offset_encode``. The
  (tile, Gaussian) pairs are sorted here, not by gsplat: gsplat's sort key is the float32 bit pattern of the
  depth, ours is the Gaussian's rank in the reference's stable (depth, index) order, so ties and float64 depths
  order exactly as in the reference. gsplat's box of tiles for a radius ``r`` covers every pixel centre within
  ``r`` (it may add a border tile whose pixels are all beyond ``r`` and so below ``alpha_min``), so the set of
  blended pixels is the reference's. Results do not depend on the tile size; gsplat's kernels run one thread per
  pixel of a tile, so they get ``min(settings.tile_size, 16)``.
- **Compositing**, two paths with the reference's results:

  * *fused* -- gsplat's ``rasterize_to_pixels`` forward and hand-written backward, used when the settings are
    the constants compiled into gsplat's kernels: ``alpha_max == 0.999``, ``alpha_min == 1/255``,
    ``transmittance_min == 1e-4``, float32 inputs, at most 512 feature channels. gsplat's rules are then the
    reference's (``alpha = min(0.999, opacity exp(-sigma))``, skipped if ``sigma < 0`` or ``alpha < 1/255``,
    a pixel stops at the first Gaussian that would bring T to ``<= 1e-4``, which is not blended), except that
    gsplat stops at ``T == 1e-4`` exactly where the reference does not; its alpha is ``1 - T``, the reference's
    ``sum w``, which are equal. Depth is composited as one more feature channel, as in the reference.
  * *exact* -- for every other setting (including the default ``alpha_max = 0.99``, which gsplat's kernels
    cannot do: they clamp at 0.999) and for float64. gsplat's ``rasterize_to_indices_in_range`` lists the
    candidate (Gaussian, pixel) pairs front to back per pixel, a few batches of every tile list at a time: it is
    given an infinite starting transmittance for the pixels still alive, which switches its own early
    termination off (0 for the pixels the reference rules have terminated, which then yield nothing), and
    opacities scaled by ``2 (1/255) / alpha_min``, so that its own ``alpha >= 1/255`` test keeps a superset
    (a factor 2 of margin for its float32 arithmetic) of the pairs the reference keeps. The pairs are then
    composited in PyTorch with the reference's rules and floating-point order
    (``alpha = min(exp(max(log opacity + power, -80)), alpha_max)``, ``power <= 0``, ``alpha >= alpha_min``,
    transmittance by ``torch.cumprod`` per pixel, a Gaussian blended only if the transmittance after it stays
    ``>= transmittance_min``, each pixel's transmittance carried from one batch range to the next); autograd
    gives the gradients, the clamp at ``alpha_max`` passing none, as in the reference. Autograd keeps about
    twenty values per blended (Gaussian, pixel) pair for the backward (about 100 bytes in float32), so this path
    needs more memory than the fused one, whose backward recomputes instead.

- **Per-Gaussian outputs** (`weight_sum`, `pixel_count`, no gradient): from the blended (Gaussian, pixel) pairs.
  ``pixel_count`` is the number of pairs of each Gaussian, ``weight_sum`` the sum over them of
  ``w = alpha T`` (T: the product of ``1 - alpha`` of the pixel's earlier blended pairs). The fused path gets
  its pairs from ``rasterize_to_indices_in_range`` with a starting transmittance of 1, which applies the same
  rules as gsplat's forward kernel, and recomputes ``alpha`` in PyTorch for the weights.

Knobs
-----
Every `RasterSettings` field is honoured. ``alpha_min`` must be ``>= 1e-30`` (else ValueError): candidate pairs
are selected in float32, with the opacity scaled by ``1/alpha_min``. ``tile_size`` only partitions work.

Availability
------------
gsplat is imported on first use, never at import time. `gsplat_installed` (an import-spec lookup) decides whether
`uw3dgs.render.rasterize` registers the backend, for 'cuda' tensors only, above the reference. If gsplat is
installed but fails to import or to build its CUDA extension, the backend warns once and serves every call with
the reference. If it is not installed, 'auto' on CUDA uses the reference after one warning (`warn_gsplat_missing`)
that says how to install it. The gsplat functions called are held in a `Kernels` table that callers can replace
(the tests put PyTorch implementations there to check this glue on CPU tensors).
"""

from __future__ import annotations

import importlib.util
import math
import threading
import warnings
from collections.abc import Callable
from dataclasses import dataclass

import torch
from torch import Tensor

from uw3dgs.cameras import Camera
from uw3dgs.render.projection import Projection, screen_gaussians
from uw3dgs.render.reference import EXP_FLOOR, rasterize_reference
from uw3dgs.render.types import RasterOutput, RasterSettings, Splats
from uw3dgs.utils.console import warn

GSPLAT_VERSION = "1.5.3"
"""The gsplat release this glue was written against (the `cuda` extra pins it)."""
INSTALL_HINT = "pip install uw3dgs[cuda]"

GSPLAT_ALPHA_MAX = 0.999
GSPLAT_ALPHA_MIN = 1.0 / 255.0
GSPLAT_TRANSMITTANCE_MIN = 1e-4
"""Constants compiled into gsplat 1.5.3's rasterization kernels (RasterizeToPixels3DGSFwd.cu, Common.h)."""
GSPLAT_MAX_CHANNELS = 513
"""rasterize_to_pixels takes at most this many channels (features + depth)."""
MAX_TILE = 16
"""Largest tile size handed to gsplat's kernels (one CUDA thread per pixel of a tile)."""
MIN_ALPHA_MIN = 1e-30
SELECTION_MARGIN = 2.0
"""Candidate pairs are selected with opacities this much larger than the exact rule needs (float32 slack)."""
BATCHES_PER_STEP = 8
"""Exact path: batches of tile_size^2 Gaussians of every tile list asked for at once (bounds the candidate pairs:
terminated pixels drop out between steps)."""


@dataclass(frozen=True)
class Kernels:
    """The gsplat functions the backend calls, with the signatures of `gsplat.cuda._wrapper` in 1.5.3."""

    isect_tiles: Callable
    """(means2d [1, N, 2], radii [1, N, 2] int32, depths [1, N], tile_size, tile_width, tile_height, sort=)
    -> (tiles_per_gauss, isect_ids int64 (tile id in bits 32+), flatten_ids int32)."""
    isect_offset_encode: Callable
    """(isect_ids sorted by tile, n_images, tile_width, tile_height) -> [1, tile_height, tile_width] int32."""
    rasterize_to_indices_in_range: Callable
    """(range_start, range_end, transmittances [1, H, W], means2d, conics, opacities, W, H, tile_size, offsets,
    flatten_ids) -> (gaussian_ids, pixel_ids, image_ids), grouped by pixel, front to back within a pixel."""
    rasterize_to_pixels: Callable | None
    """(means2d, conics, colors [1, N, C], opacities, W, H, tile_size, offsets, flatten_ids) -> ([1, H, W, C],
    [1, H, W, 1]), differentiable; None: always take the exact path."""


_lock = threading.Lock()
_state: dict[str, object] = {}


def gsplat_installed() -> bool:
    """Whether gsplat can be found, without importing it."""
    try:
        return importlib.util.find_spec("gsplat") is not None
    except (ImportError, ValueError):
        return False


def _warn_once(key: str, message: str) -> None:
    """Warn with `message` the first time `key` comes up in this process, never again.

    A RuntimeWarning (as is the failed kernel load's), not console.warn: callers (and tests) filter or catch these
    fallbacks with `warnings`."""
    with _lock:
        if _state.get(key):
            return
        _state[key] = True
    warnings.warn(message, RuntimeWarning, stacklevel=4)


def warn_gsplat_missing() -> None:
    """One warning per process: CUDA tensors are rendered by the slow reference because gsplat is missing."""
    _warn_once(
        "missing_warned",
        "uw3dgs: CUDA tensors are rendered with the pure-PyTorch reference rasterizer ('torch'), because the fast "
        f"CUDA backend 'gsplat' needs gsplat=={GSPLAT_VERSION}, which is not installed. Install it with "
        f"`{INSTALL_HINT}` (gsplat compiles its CUDA kernels on first use; that needs the CUDA toolkit, nvcc).",
    )


def _import_cuda_kernels() -> Kernels:
    """gsplat's CUDA functions; raises if gsplat or its compiled extension cannot be loaded."""
    import gsplat
    from gsplat.cuda import _wrapper
    from gsplat.cuda._backend import _C  # builds the extension on first use (minutes)

    if _C is None:
        raise RuntimeError("gsplat found no CUDA toolkit (nvcc) to build its CUDA extension with")
    if gsplat.__version__ != GSPLAT_VERSION:
        warn(f"the 'gsplat' backend was written and tested against gsplat {GSPLAT_VERSION}, found "
             f"{gsplat.__version__}; `{INSTALL_HINT}` installs the tested version.")
    return Kernels(
        isect_tiles=_wrapper.isect_tiles,
        isect_offset_encode=_wrapper.isect_offset_encode,
        rasterize_to_indices_in_range=_wrapper.rasterize_to_indices_in_range,
        rasterize_to_pixels=_wrapper.rasterize_to_pixels,
    )


def load_kernels() -> Kernels | None:
    """gsplat's CUDA kernels (imported and built on the first call); None, after one warning, if that fails."""
    with _lock:
        if "kernels" in _state:
            return _state["kernels"]  # type: ignore[return-value]
        kernels = None
        try:
            kernels = _import_cuda_kernels()
        except Exception as exc:  # noqa: BLE001 - any failure means: fall back to the reference
            _state["error"] = f"{type(exc).__name__}: {exc}"
            warnings.warn(
                "uw3dgs: could not load gsplat's CUDA kernels (backend 'gsplat'); falling back to the pure-PyTorch "
                f"reference, which is much slower. Reason: {str(exc).strip()[-500:]}",
                RuntimeWarning,
                stacklevel=3,
            )
        _state["kernels"] = kernels
        return kernels


def fused_path_applies(settings: RasterSettings, dtype: torch.dtype, channels: int) -> bool:
    """Whether gsplat's fused rasterize_to_pixels reproduces the reference for these settings (see the module doc)."""
    return (
        settings.alpha_max == GSPLAT_ALPHA_MAX
        and settings.alpha_min == GSPLAT_ALPHA_MIN
        and settings.transmittance_min == GSPLAT_TRANSMITTANCE_MIN
        and dtype == torch.float32
        and channels + 1 <= GSPLAT_MAX_CHANNELS
    )


def _warn_exact_path(settings: RasterSettings, dtype: torch.dtype) -> None:
    """One warning per process: CUDA renders take the slower exact path because the settings are not gsplat's."""
    _warn_once(
        "exact_warned",
        f"uw3dgs: gsplat's fused CUDA kernels have alpha_max={GSPLAT_ALPHA_MAX}, alpha_min=1/255, "
        f"transmittance_min={GSPLAT_TRANSMITTANCE_MIN} and float32 compiled in; these renders use alpha_max="
        f"{settings.alpha_max}, alpha_min={settings.alpha_min}, transmittance_min={settings.transmittance_min}, "
        f"{dtype}, so they take the exact path (the reference's numbers, slower and more memory). For gsplat's speed "
        f"pass --model.raster.alpha-max {GSPLAT_ALPHA_MAX} (the default 0.99 is 3DGS's).",
    )


def _check_settings(settings: RasterSettings) -> None:
    if not settings.alpha_min >= MIN_ALPHA_MIN:
        raise ValueError(
            f"the 'gsplat' backend needs RasterSettings.alpha_min >= {MIN_ALPHA_MIN} (got {settings.alpha_min}): it "
            "selects candidate pairs in float32 with opacities scaled by 1/alpha_min; use backend 'torch' instead"
        )
    if settings.tile_size < 1:
        raise ValueError(f"RasterSettings.tile_size must be >= 1, got {settings.tile_size}")


@dataclass
class _Tiles:
    """gsplat's tile lists of one view, sorted in the reference's (tile, depth, index) order."""

    offsets: Tensor
    """[1, tiles_y, tiles_x] int32 start of each tile's list in flatten_ids."""
    flatten_ids: Tensor
    """[pairs] int32 Gaussian index of each (tile, Gaussian) pair."""
    tile_size: int
    batches: int
    """Batches of tile_size^2 Gaussians in the longest tile list (the range rasterize_to_indices_in_range needs)."""


def _bin(proj: Projection, width: int, height: int, tile_size: int, kernels: Kernels) -> _Tiles | None:
    """Tile lists from gsplat's isect_tiles, re-sorted by (tile, depth rank); None if no pair."""
    n = len(proj.radii)
    tiles_x = -(-width // tile_size)
    tiles_y = -(-height // tile_size)
    if n == 0 or not bool((proj.radii > 0).any()):
        return None
    means2d = proj.means2d.detach().float().contiguous()
    radii = proj.radii[:, None].expand(n, 2).contiguous()
    depths = proj.depths.detach().float().contiguous()
    _, isect_ids, flatten_ids = kernels.isect_tiles(
        means2d[None], radii[None], depths[None], tile_size, tiles_x, tiles_y, sort=False
    )
    if len(flatten_ids) == 0:
        return None
    order = torch.argsort(proj.depths.detach(), stable=True)
    rank = torch.empty_like(order)
    rank[order] = torch.arange(n, device=order.device)
    key = (isect_ids >> 32) * n + rank[flatten_ids.long()]  # one image: bits 32+ hold the tile id
    perm = torch.argsort(key)  # keys are unique
    isect_ids = isect_ids[perm].contiguous()
    flatten_ids = flatten_ids[perm].contiguous()
    offsets = kernels.isect_offset_encode(isect_ids, 1, tiles_x, tiles_y)
    ends = torch.cat([offsets.flatten().long(), offsets.new_full((1,), len(flatten_ids)).long()])
    longest = int(torch.diff(ends).max())
    return _Tiles(offsets=offsets, flatten_ids=flatten_ids, tile_size=tile_size,
                  batches=max(1, -(-longest // tile_size**2)))  # fmt: skip


def _pairs(
    tiles: _Tiles, proj: Projection, opacities: Tensor, start_transmittance: Tensor, batches: tuple[int, int],
    kernels: Kernels,
) -> tuple[Tensor, Tensor]:  # fmt: skip
    """(Gaussian, pixel) pairs from gsplat's rasterize_to_indices_in_range over the given batches of every tile's
    list: grouped by pixel, front to back within a pixel. `start_transmittance` is [H, W] float32."""
    height, width = start_transmittance.shape
    gauss, pixel, _ = kernels.rasterize_to_indices_in_range(
        batches[0], batches[1], start_transmittance[None].contiguous(),
        proj.means2d.detach().float().contiguous()[None], proj.conics.detach().float().contiguous()[None],
        opacities.detach().float().contiguous()[None], width, height, tiles.tile_size, tiles.offsets,
        tiles.flatten_ids,
    )  # fmt: skip
    return gauss.long(), pixel.long()


def _pair_alpha(
    means2d: Tensor, conics: Tensor, opacities: Tensor, gauss: Tensor, pixel: Tensor, width: int, alpha_max: float
) -> tuple[Tensor, Tensor, Tensor]:
    """(alpha clamped at alpha_max, exponent log(opacity) + power, log(opacity)) per pair, in the reference's
    floating-point order; differentiable, no gradient through the clamp (as in the reference)."""
    dtype = means2d.dtype
    px = (pixel % width).to(dtype) + 0.5
    py = torch.div(pixel, width, rounding_mode="floor").to(dtype) + 0.5
    mean = means2d[gauss]
    conic = conics[gauss]
    dx = px - mean[:, 0]
    dy = py - mean[:, 1]
    a, b, c = conic.unbind(-1)
    log_opacity = torch.log(opacities[gauss])
    exponent = (-0.5 * c * dy * dy + log_opacity) + (-0.5 * a * dx * dx)
    exponent = torch.addcmul(exponent, -b * dy, dx)
    raw = exponent.clamp(min=EXP_FLOOR).exp()
    alpha = torch.where(raw < alpha_max, raw, torch.full_like(raw, alpha_max))
    return alpha, exponent, log_opacity


def _cumprod_per_pixel(factors: Tensor, pixel: Tensor, start: Tensor | None = None) -> tuple[Tensor, Tensor]:
    """Products of the factors of the earlier pairs of the same pixel (exclusive) and up to the pair (inclusive).

    Pairs are grouped by pixel, in compositing order; `start` ([pixels], default 1) is each pixel's product
    before its first pair. The products are `torch.cumprod` rows (the reference's op, in the same order), one
    dense [pixels, longest + 1] block per power-of-two bucket of list lengths, so padding stays below 2x.
    Differentiable in `factors`.
    """
    m = len(factors)
    if m == 0:
        return factors.new_ones(0), factors.new_ones(0)
    device = factors.device
    pixels, counts = torch.unique_consecutive(pixel, return_counts=True)
    starts = torch.cumsum(counts, 0) - counts
    segment = torch.repeat_interleave(torch.arange(len(counts), device=device), counts)
    position = torch.arange(m, device=device) - starts[segment]
    bucket = torch.ceil(torch.log2(counts.double())).long()  # length 1 -> 0, 2 -> 1, 3..4 -> 2, ...
    pair_bucket = bucket[segment]
    index_pieces, exclusive_pieces, inclusive_pieces = [], [], []
    for b in torch.unique(bucket).tolist():
        segments = (bucket == b).nonzero().squeeze(1)
        row_of_segment = torch.full((len(counts),), -1, dtype=torch.long, device=device)
        row_of_segment[segments] = torch.arange(len(segments), device=device)
        members = (pair_bucket == b).nonzero().squeeze(1)
        rows = row_of_segment[segment[members]]
        cols = position[members]
        dense = factors.new_ones(len(segments), int(counts[segments].max()) + 1)
        if start is not None:
            dense[:, 0] = start[pixels[segments]]
        dense = dense.index_put((rows, cols + 1), factors[members])
        products = torch.cumprod(dense, dim=1)
        index_pieces.append(members)
        exclusive_pieces.append(products[rows, cols])
        inclusive_pieces.append(products[rows, cols + 1])
    order = torch.cat(index_pieces)
    inverse = torch.empty_like(order)
    inverse[order] = torch.arange(m, device=device)
    return torch.cat(exclusive_pieces)[inverse], torch.cat(inclusive_pieces)[inverse]


def _per_gaussian(gauss: Tensor, weights: Tensor, n: int) -> tuple[Tensor, Tensor]:
    """weight_sum and pixel_count from the blended pairs."""
    weight_sum = weights.new_zeros(n).index_add_(0, gauss, weights)
    pixel_count = torch.bincount(gauss, minlength=n).to(torch.int32)
    return weight_sum, pixel_count


@torch.no_grad()
def _blended_pairs(
    proj: Projection, opacities: Tensor, tiles: _Tiles | None, width: int, height: int, settings: RasterSettings,
    kernels: Kernels,
) -> tuple[Tensor, Tensor, Tensor]:  # fmt: skip
    """(Gaussian, pixel, weight) of every pair the reference blends, grouped by pixel, front to back.

    The tile lists are walked BATCHES_PER_STEP batches at a time. Each step asks gsplat for the candidate pairs
    of the pixels still alive (starting transmittance inf: its own termination is off; 0 for terminated pixels,
    which then yield nothing), with opacities scaled so that its alpha >= 1/255 test keeps a superset of the
    reference's pairs, then applies the reference's rules, carrying each pixel's transmittance to the next step.
    """
    dtype, device = opacities.dtype, opacities.device
    empty = torch.zeros(0, dtype=torch.long, device=device)
    if tiles is None:
        return empty, empty, opacities.new_zeros(0)
    means2d, conics = proj.means2d.detach().to(dtype), proj.conics.detach().to(dtype)
    opacities = opacities.detach()
    selection = (opacities.double() * (SELECTION_MARGIN * GSPLAT_ALPHA_MIN / settings.alpha_min)).clamp(max=1e30)
    transmittance = opacities.new_ones(height * width)
    alive = torch.ones(height * width, dtype=torch.bool, device=device)
    found = []
    for first in range(0, tiles.batches, BATCHES_PER_STEP):
        start = torch.where(alive, math.inf, 0.0).float().view(height, width)
        batches = (first, min(first + BATCHES_PER_STEP, tiles.batches))
        gauss, pixel = _pairs(tiles, proj, selection, start, batches, kernels)
        alpha, exponent, log_opacity = _pair_alpha(means2d, conics, opacities, gauss, pixel, width,
                                                   settings.alpha_max)  # fmt: skip
        hit = (exponent <= log_opacity) & (alpha >= settings.alpha_min)
        gauss, pixel, alpha = gauss[hit], pixel[hit], alpha[hit]
        before, after = _cumprod_per_pixel(1.0 - alpha, pixel, start=transmittance)
        kept = after >= settings.transmittance_min
        alive[pixel[~kept]] = False  # a pixel stops at its first Gaussian that would bring T below the minimum
        gauss, pixel, after = gauss[kept], pixel[kept], after[kept]
        transmittance.scatter_reduce_(0, pixel, after, reduce="amin")  # T after the pixel's last blended pair
        found.append((gauss, pixel, (alpha * before)[kept]))
    gauss, pixel, weights = (torch.cat(parts) for parts in zip(*found, strict=True))
    order = torch.argsort(pixel, stable=True)  # steps were appended in order: front to back within a pixel
    return gauss[order], pixel[order], weights[order]


def _composite_exact(
    proj: Projection, opacities: Tensor, feats: Tensor, tiles: _Tiles | None, width: int, height: int,
    settings: RasterSettings, kernels: Kernels,
) -> tuple[Tensor, Tensor, Tensor]:  # fmt: skip
    """[H, W, F] image of feats (the last channel all ones, giving alpha), weight_sum, pixel_count."""
    n, dtype = len(feats), feats.dtype
    means2d, conics, opacities = proj.means2d.to(dtype), proj.conics.to(dtype), opacities.to(dtype)
    gauss, pixel, weights = _blended_pairs(proj, opacities, tiles, width, height, settings, kernels)
    weight_sum, pixel_count = _per_gaussian(gauss, weights, n)
    # the blended pairs again, differentiably: autograd keeps a few tensors per pair for the backward
    alpha, _, _ = _pair_alpha(means2d, conics, opacities, gauss, pixel, width, settings.alpha_max)
    before, _ = _cumprod_per_pixel(1.0 - alpha, pixel)
    contributions = (alpha * before)[:, None] * feats[gauss]
    image = feats.new_zeros(height * width, feats.shape[1]).index_add(0, pixel, contributions)
    return image.view(height, width, -1), weight_sum, pixel_count


def _composite_fused(
    proj: Projection, opacities: Tensor, feats: Tensor, tiles: _Tiles, width: int, height: int, kernels: Kernels
) -> tuple[Tensor, Tensor, Tensor, Tensor]:
    """gsplat's rasterize_to_pixels: [H, W, F] image of feats, [H, W] alpha, weight_sum, pixel_count."""
    image, alpha = kernels.rasterize_to_pixels(
        proj.means2d[None], proj.conics[None], feats[None], opacities[None], width, height, tiles.tile_size,
        tiles.offsets, tiles.flatten_ids,
    )  # fmt: skip
    with torch.no_grad():
        start = torch.ones(height, width, dtype=torch.float32, device=opacities.device)  # gsplat's own termination
        gauss, pixel = _pairs(tiles, proj, opacities, start, (0, tiles.batches), kernels)
        pair_alpha, _, _ = _pair_alpha(proj.means2d.detach(), proj.conics.detach(), opacities.detach(), gauss, pixel,
                                       width, GSPLAT_ALPHA_MAX)  # fmt: skip
        before, _ = _cumprod_per_pixel(1.0 - pair_alpha, pixel)
        weight_sum, pixel_count = _per_gaussian(gauss, pair_alpha * before, len(feats))
    return image[0], alpha[0, ..., 0], weight_sum, pixel_count


def rasterize_gsplat(splats: Splats, camera: Camera, settings: RasterSettings,
                     projection: RasterOutput | None = None, kernels: Kernels | None = None) -> RasterOutput:
    """Same contract and numbers as `rasterize_reference`, with gsplat's kernels ('gsplat' backend).

    `kernels` replaces gsplat's CUDA functions (default: load them; CUDA tensors only). If they cannot be loaded,
    the reference renders the view (after one warning).
    """
    _check_settings(settings)
    device = splats.means.device
    if kernels is None:
        if device.type != "cuda":
            raise ValueError(
                f"the 'gsplat' backend runs on CUDA tensors, got {device.type}; use backend 'auto', 'cpu' or "
                "'torch' there"
            )
        kernels = load_kernels()
        if kernels is None:
            return rasterize_reference(splats, camera, settings, projection)

    opacities, features, width, height = splats.opacities, splats.features, camera.width, camera.height
    proj = screen_gaussians(splats, camera, settings, projection)
    tiles = _bin(proj, width, height, min(settings.tile_size, MAX_TILE), kernels)
    feats = torch.cat([features, proj.depths[:, None]], dim=1)  # depth composites like a feature
    dtype = torch.promote_types(torch.promote_types(proj.means2d.dtype, opacities.dtype), feats.dtype)
    channels = features.shape[1]
    fused = (
        tiles is not None and kernels.rasterize_to_pixels is not None and fused_path_applies(settings, dtype, channels)
    )
    if not fused and device.type == "cuda":
        _warn_exact_path(settings, dtype)
    if fused:
        image, alpha, weight_sum, pixel_count = _composite_fused(proj, opacities, feats, tiles, width, height, kernels)
    else:
        feats = torch.cat([feats.to(dtype), feats.new_ones((len(feats), 1), dtype=dtype)], dim=1)  # ones -> alpha
        image, weight_sum, pixel_count = _composite_exact(proj, opacities, feats, tiles, width, height, settings,
                                                          kernels)  # fmt: skip
        alpha = image[..., channels + 1]
    return RasterOutput(
        render=image[..., :channels],
        alpha=alpha,
        depth=image[..., channels],
        means2d=proj.means2d,
        radii=proj.radii,
        depths=proj.depths,
        conics=proj.conics,
        weight_sum=weight_sum,
        pixel_count=pixel_count,
    )
