"""Inputs and outputs shared by every rasterizer backend."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Protocol

from torch import Tensor

from uw3dgs.cameras import Camera
from uw3dgs.options import CheckedConfig, OptionError, check_number


@dataclass(frozen=True)
class RasterSettings(CheckedConfig):
    """Numerical choices of 3DGS rasterization; every backend honours all of them."""

    tile_size: int = 16
    """Side of the square screen tiles Gaussians are binned into, in pixels."""
    near_plane: float = 0.01
    """Gaussians whose centre is closer than this (camera z) are culled."""
    far_plane: float = 1e10
    """Gaussians whose centre is farther than this (camera z) are culled."""
    eps2d: float = 0.3
    """Screen-space low-pass filter added to the 2D covariance diagonal (pixels^2), as in 3DGS."""
    alpha_min: float = 1.0 / 255.0
    """Contributions with alpha below this are skipped."""
    alpha_max: float = 0.99
    """Alpha is clamped to this so transmittance never reaches zero."""
    transmittance_min: float = 1e-4
    """Early ray termination: a Gaussian that would bring T below this is not blended, nor any after it."""
    backend: str = "auto"
    """Rasterizer backend: 'auto' picks the fastest available for the tensors' device."""

    def check_options(self) -> None:
        check_number(self, "tile_size", ge=1, integer=True)
        check_number(self, "near_plane", gt=0)
        check_number(self, "far_plane", gt=self.near_plane if isinstance(self.near_plane, (int, float)) else 0)
        check_number(self, "eps2d", ge=0)
        check_number(self, "alpha_min", ge=0, lt=1)
        check_number(self, "alpha_max", gt=0, le=1)
        check_number(self, "transmittance_min", ge=0, lt=1)
        if self.alpha_min >= self.alpha_max:
            raise OptionError("alpha_max", f"must be larger than alpha_min ({self.alpha_min:g}), "
                                           f"got {self.alpha_max:g}")


@dataclass(frozen=True)
class Splats:
    """The activated 3D Gaussians one render draws (gsplat's names), all of one dtype and device.

    means [N, 3] world positions; quats [N, 4] rotations (w, x, y, z), normalised by the rasterizer; scales [N, 3]
    standard deviations along the rotated axes (already exp'd); opacities [N] in [0, 1] (already sigmoid'd);
    features [N, C] the channels composited per pixel (colours, or any per-Gaussian values)."""

    means: Tensor
    quats: Tensor
    scales: Tensor
    opacities: Tensor
    features: Tensor


@dataclass(frozen=True)
class TileLists:
    """The compiled backend's binning of one render at `tile_size`: `tensors` = (tile starts [tiles + 1] int64,
    Gaussian of each pair sorted by tile then depth [pairs] int32, each sorted pair's slot [pairs] int64, each
    Gaussian's first slot [N + 1] int64). A render of the same view and Gaussians with opacities no higher composites
    over them as over its own (uw3dgs/kernels/compositing.cpp, composite_forward)."""

    tile_size: int
    tensors: tuple[Tensor, ...]


@dataclass
class RasterOutput:
    """What one view's rasterization returns.

    Per pixel (H x W): `render` = sum_i w_i f_i, `alpha` = sum_i w_i, `depth` = sum_i w_i z_i with
    w_i = alpha_i T_i the blending weights and z_i the camera-space z of Gaussian i's centre
    (divide by `alpha` for the expected depth). Per Gaussian (N): `means2d` is the projected centre in
    pixels and is part of the autograd graph (call `retain_grad()` before backward for the
    screen-space gradient used by densification); `radii` is the screen radius in pixels (0 = culled);
    `depths` the camera-space z; `conics` the entries (a, b, c) of the inverse 2D covariance [[a, b], [b, c]];
    `weight_sum` the sum of the Gaussian's blending weights over the view's pixels and `pixel_count` the
    number of pixels it was blended into (both without gradient). A later render of the same view may reuse
    means2d, conics, depths and radii (`rasterize`'s `projection`), and `tile_lists`, its binning, where the
    compiled backend made it for a backward (else None).

    Shapes and types: render [H, W, C]; alpha and depth [H, W]; means2d [N, 2] in pixels, where
    pixel (u, v) has its centre at (u + 0.5, v + 0.5) and a point projects to (fx x/z + cx, fy y/z + cy);
    conics [N, 3] in pixels^-2; radii and pixel_count int32; depths and weight_sum in the input dtype.
    Nothing is composed over a background: callers add (1 - alpha[..., None]) * background.
    """

    render: Tensor
    alpha: Tensor
    depth: Tensor
    means2d: Tensor
    radii: Tensor
    depths: Tensor
    conics: Tensor
    weight_sum: Tensor
    pixel_count: Tensor
    tile_lists: TileLists | None = None


class RasterFn(Protocol):
    """A rasterizer backend (`rasterize.register_backend`): `rasterize_reference`'s contract and numbers. It renders
    `splats` from `camera` (any float dtype of the splats; the camera is read in it) with `settings`, reusing
    `projection`'s screen-space Gaussians where given (see `rasterize`)."""

    def __call__(self, splats: Splats, camera: Camera, settings: RasterSettings,
                 projection: RasterOutput | None = None) -> RasterOutput: ...
