"""Colour-mapped scalar fields and image grids for logs and side-by-side comparisons (no matplotlib)."""

from __future__ import annotations

import math

import numpy as np
import torch
from torch import Tensor

ArrayLike = Tensor | np.ndarray

# Turbo colormap, degree-5 polynomial fit per channel (rows: coefficients of x^0 .. x^5; columns: R, G, B).
# Colormap design: Anton Mikhailov; polynomial approximation: Ruofei Du (Google LLC, 2019, Apache-2.0).
_TURBO_COEFFS = (
    (0.13572138, 0.09140261, 0.10667330),
    (4.61539260, 2.19418839, 12.64194608),
    (-42.66032258, 4.84296658, -60.58204836),
    (132.13108234, -14.18503333, 110.36276771),
    (-152.94239396, 4.27729857, -89.90310912),
    (59.28637943, 2.82956604, 27.34824973),
)

ROBUST_PERCENTILES = (1.0, 99.0)
"""Default colour range of `apply_colormap`: these percentiles of the valid values, so a few outliers
(floaters, sky) do not squeeze everything else into one colour."""

MIN_DEPTH_ALPHA = 0.5
"""`depth_to_image` draws pixels whose accumulated opacity is below this as empty (black)."""

SEPARATOR_PX = 2
"""Width of the white lines `image_grid` draws between tiles."""


def _turbo(t: Tensor) -> Tensor:
    """Turbo colours [..., 3] in [0, 1] for t in [0, 1] (0 = dark blue, 1 = dark red)."""
    coeffs = torch.tensor(_TURBO_COEFFS, dtype=t.dtype, device=t.device)
    powers = torch.stack([t**k for k in range(len(_TURBO_COEFFS))], dim=-1)
    return (powers @ coeffs).clamp(0.0, 1.0)


def _robust_range(values: Tensor) -> tuple[float, float]:
    """Percentile range of finite values; (0, 1) when there are none, so callers need no special case."""
    if values.numel() == 0:
        return 0.0, 1.0
    lo, hi = np.percentile(values.cpu().double().numpy(), ROBUST_PERCENTILES)
    return float(lo), float(hi)


def apply_colormap(
    x: ArrayLike, vmin: float | None = None, vmax: float | None = None, mask: ArrayLike | None = None
) -> Tensor:
    """Map a scalar field [H, W] to turbo colours [H, W, 3] float32 in [0, 1], on x's device.

    Values are scaled linearly from [vmin, vmax] to [0, 1] and clipped; a bound left as None is the
    1st/99th percentile of the valid values. Invalid pixels (NaN, +-inf, or False in the optional
    boolean `mask`) are drawn black and never influence the range.
    """
    x = torch.as_tensor(x).detach().float()  # a picture needs no autograd graph
    if x.ndim != 2:
        raise ValueError(f"apply_colormap expects a [H, W] field, got shape {tuple(x.shape)}")
    valid = torch.isfinite(x)
    if mask is not None:
        valid &= torch.as_tensor(mask, device=x.device, dtype=torch.bool)
    if vmin is None or vmax is None:
        lo, hi = _robust_range(x[valid])
        vmin = lo if vmin is None else vmin
        vmax = hi if vmax is None else vmax
    span = max(vmax - vmin, 1e-12)  # a constant field maps to the bottom colour instead of NaN
    colors = _turbo(((x - vmin) / span).clamp(0.0, 1.0))
    return torch.where(valid[..., None], colors, torch.zeros_like(colors))


def depth_to_image(depth: ArrayLike, alpha: ArrayLike | None = None) -> Tensor:
    """Turbo-coloured depth [H, W, 3] with near = warm (red) and far = cold (blue).

    `depth` is an expected depth or range map [H, W] (already divided by the accumulated opacity);
    the optional `alpha` [H, W] marks pixels below MIN_DEPTH_ALPHA as empty, since a depth averaged
    over a few faint Gaussians is mostly noise. Empty, non-finite (e.g. inf for open water) and
    non-positive depths are drawn black and do not affect the colour range.
    """
    depth = torch.as_tensor(depth).detach().float()
    valid = torch.isfinite(depth) & (depth > 0)
    if alpha is not None:
        valid &= torch.as_tensor(alpha, device=depth.device) >= MIN_DEPTH_ALPHA
    # Negating puts the nearest depths at the top (red end) of the colormap.
    return apply_colormap(-depth, mask=valid)


def to_uint8(img: ArrayLike) -> np.ndarray:
    """Float image in [0, 1] -> uint8 numpy array for saving; out-of-range values clip, NaN -> 0. A uint8 numpy image
    (already 8-bit, as `labelled_row` makes) is returned as it is: read as [0, 1] floats it would clip to white."""
    if isinstance(img, np.ndarray) and img.dtype == np.uint8:
        return img
    arr = img.detach().float().cpu().numpy() if isinstance(img, Tensor) else np.asarray(img, dtype=np.float32)
    return np.rint(np.nan_to_num(arr, nan=0.0).clip(0.0, 1.0) * 255.0).astype(np.uint8)


def image_grid(images: list[ArrayLike], ncols: int | None = None) -> Tensor:
    """Tile equally sized [H, W, 3] images row-major into one float32 CPU image with white separators.

    `ncols` defaults to all images in one row (e.g. GT | render | depth); unused cells stay white.
    """
    if not images:
        raise ValueError("image_grid needs at least one image")
    tiles = [torch.as_tensor(img).detach().float().cpu() for img in images]
    shape = tiles[0].shape
    if len(shape) != 3 or shape[-1] != 3 or any(tile.shape != shape for tile in tiles):
        shapes = [tuple(tile.shape) for tile in tiles]
        raise ValueError(f"image_grid needs [H, W, 3] images of one size, got {shapes}")
    ncols = len(tiles) if ncols is None else ncols
    if ncols < 1:
        raise ValueError(f"ncols must be positive, got {ncols}")
    nrows = math.ceil(len(tiles) / ncols)
    h, w = shape[0], shape[1]
    step_y, step_x = h + SEPARATOR_PX, w + SEPARATOR_PX
    grid = torch.ones(nrows * step_y - SEPARATOR_PX, ncols * step_x - SEPARATOR_PX, 3)
    for i, tile in enumerate(tiles):
        row, col = divmod(i, ncols)
        grid[row * step_y : row * step_y + h, col * step_x : col * step_x + w] = tile
    return grid
