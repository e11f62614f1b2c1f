"""EWA projection of 3D Gaussians to screen-space 2D Gaussians (Zwicker et al. 2002, as in 3DGS).

Pixel convention: pixel (u, v) (column u, row v) covers [u, u+1) x [v, v+1) and has its centre at
(u + 0.5, v + 0.5). A camera-space point (x, y, z) projects to (fx x/z + cx, fy y/z + cy) in that same
continuous coordinate system, so an image-centred principal point is cx = width/2, cy = height/2
(COLMAP's convention).
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import Tensor

from uw3dgs.cameras import Camera
from uw3dgs.render.types import RasterOutput, RasterSettings, Splats

FOV_CLAMP = 1.3
"""The Jacobian is evaluated at most this many half-fields-of-view off-axis, as in 3DGS."""


@dataclass
class Projection:
    """Screen-space Gaussians of one view; every field is indexed like the input Gaussians."""

    means2d: Tensor
    """[N, 2] projected centres in pixels (see the module docstring for the convention)."""
    conics: Tensor
    """[N, 3] inverse 2D covariance (a, b, c) = [[a, b], [b, c]]^-1 entries, pixels^-2."""
    depths: Tensor
    """[N] camera-space z of the centres."""
    radii: Tensor
    """[N] int32 half-side of the screen-space bounding square in pixels; 0 for culled Gaussians."""
    valid: Tensor
    """[N] bool, radii > 0: in the depth range, visible above alpha_min and overlapping the image."""


def reused_projection(raster: RasterOutput) -> Projection:
    """The screen-space Gaussians of an earlier render (detached), for a render of the same view and geometry."""
    radii = raster.radii
    return Projection(means2d=raster.means2d.detach(), conics=raster.conics.detach(), depths=raster.depths.detach(),
                      radii=radii, valid=radii > 0)


def screen_gaussians(splats: Splats, camera: Camera, settings: RasterSettings,
                     projection: RasterOutput | None = None) -> Projection:
    """The splats' screen-space Gaussians in `camera`: `projection`'s (an earlier render's, see `rasterize`) where
    given, else projected."""
    if projection is not None:
        return reused_projection(projection)
    return project_gaussians(splats.means, splats.quats, splats.scales, splats.opacities, camera.viewmat, camera.K,
                             camera.width, camera.height, settings)


def quat_to_rotmat(quats: Tensor) -> Tensor:
    """[N, 4] (w, x, y, z) quaternions, not necessarily unit, to [N, 3, 3] rotation matrices."""
    w, x, y, z = torch.nn.functional.normalize(quats, dim=-1).unbind(-1)
    rows = (
        1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y),
        2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x),
        2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y),
    )  # fmt: skip
    return torch.stack(rows, dim=-1).reshape(*quats.shape[:-1], 3, 3)


def _perspective_jacobian(p_cam: Tensor, K: Tensor, width: int, height: int) -> Tensor:
    """[N, 2, 3] Jacobian of the pinhole projection at the camera-space centres.

    Off-axis coordinates are clamped to 1.3x the half field of view so Gaussians far outside the
    image do not get wildly stretched footprints (3DGS's guard against the affine approximation).
    """
    fx, fy = K[0, 0], K[1, 1]
    x, y, z = p_cam.unbind(-1)
    lim_x = FOV_CLAMP * 0.5 * width / fx
    lim_y = FOV_CLAMP * 0.5 * height / fy
    tx = torch.clamp(x / z, -lim_x, lim_x) * z
    ty = torch.clamp(y / z, -lim_y, lim_y) * z
    zero = torch.zeros_like(z)
    rows = (fx / z, zero, -fx * tx / (z * z), zero, fy / z, -fy * ty / (z * z))
    return torch.stack(rows, dim=-1).reshape(-1, 2, 3)


def _opacity_extent(opacities: Tensor, alpha_min: float) -> Tensor:
    """Mahalanobis distance beyond which opacity * exp(-d^2/2) < alpha_min (0 if never above)."""
    ratio = (opacities / alpha_min).clamp_min(1.0)
    return torch.sqrt(2.0 * torch.log(ratio))


def project_gaussians(
    means: Tensor,
    quats: Tensor,
    scales: Tensor,
    opacities: Tensor,
    viewmat: Tensor,
    K: Tensor,
    width: int,
    height: int,
    settings: RasterSettings,
) -> Projection:
    """Project Gaussians (scales already exp'd, opacities already sigmoid'd) into one view.

    cov2d = J W R S S^T R^T W^T J^T + eps2d I. The radius is opacity-aware (like gsplat): the
    bounding square contains every pixel where the Gaussian's alpha can reach alpha_min, so tiling
    never drops a contribution the blending rules would keep.
    """
    viewmat = viewmat.to(means)
    K = K.to(means)
    W, t = viewmat[:3, :3], viewmat[:3, 3]
    p_cam = means @ W.T + t
    depths = p_cam[:, 2]
    in_range = (depths >= settings.near_plane) & (depths <= settings.far_plane)
    # Culled Gaussians get a harmless depth so nothing below divides by ~0 (their outputs are masked).
    z_safe = torch.where(in_range, depths, torch.ones_like(depths))
    p_cam = torch.cat([p_cam[:, :2], z_safe[:, None]], dim=-1)

    means2d = p_cam[:, :2] / z_safe[:, None] * torch.stack([K[0, 0], K[1, 1]]) + K[:2, 2]

    M = quat_to_rotmat(quats) * scales[:, None, :]  # R S: Sigma = M M^T
    JWM = _perspective_jacobian(p_cam, K, width, height) @ W @ M
    cov2d = JWM @ JWM.transpose(-1, -2)
    a = cov2d[:, 0, 0] + settings.eps2d
    b = cov2d[:, 0, 1]
    c = cov2d[:, 1, 1] + settings.eps2d
    det = a * c - b * b
    det_ok = det > 0
    det_safe = torch.where(det_ok, det, torch.ones_like(det))
    conics = torch.stack([c, -b, a], dim=-1) / det_safe[:, None]

    radii = _radii(means2d.detach(), a.detach(), c.detach(), det.detach(), opacities.detach(), width, height,
                   settings.alpha_min)  # fmt: skip
    valid = in_range & det_ok & (radii > 0)
    radii = torch.where(valid, radii, torch.zeros_like(radii))
    return Projection(means2d=means2d, conics=conics, depths=depths, radii=radii, valid=valid)


def _radii(
    means2d: Tensor, a: Tensor, c: Tensor, det: Tensor, opacities: Tensor, width: int, height: int,
    alpha_min: float,
) -> Tensor:  # fmt: skip
    """Integer bounding-square half-sides, 0 where the square covers no pixel centre."""
    mid = 0.5 * (a + c)
    lambda_max = mid + torch.sqrt((mid * mid - det).clamp_min(0.0))
    radius = torch.ceil(_opacity_extent(opacities, alpha_min) * torch.sqrt(lambda_max.clamp_min(0.0)))
    radius = torch.nan_to_num(radius, nan=0.0).clamp(max=2.0**30)
    x, y = means2d.unbind(-1)
    # Pixel centres span [0.5, width - 0.5] x [0.5, height - 0.5].
    on_screen = (x + radius >= 0.5) & (x - radius <= width - 0.5)
    on_screen &= (y + radius >= 0.5) & (y - radius <= height - 0.5)
    return torch.where(on_screen, radius, torch.zeros_like(radius)).to(torch.int32)
