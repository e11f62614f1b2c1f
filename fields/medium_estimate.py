"""A first estimate of a homogeneous medium from the initial (SfM) points, before any Gaussian is trained.

Every initial point p is projected into every training view k that sees it in front of the camera; the
pixel colour there is an observation I_pk of the same surface at range z_pk. The formation model
    I_pk = J_p exp(-beta_D z_pk) + B_inf (1 - exp(-beta_B z_pk))
is then fitted to all observations at once: one unknown clean colour J_p per point and one homogeneous
(beta_D, beta_B, B_inf). This is the classic SeaThru-style estimate (Akkaynak & Treibitz 2019): the
attenuation is read off how a point's colour changes with range, the backscatter off how dark points
brighten with range. It needs the camera-to-point range to vary across views, which it does for the
forward-looking or surveying captures underwater datasets are made of.

Points alone pin beta_D well but leave (B_inf, beta_B) on a flat valley: only the backscatter curve
B_inf (1 - exp(-beta_B z)) over the observed ranges is seen. Where the views show open water, its colour
is B_inf itself (`open_water_color`), and with B_inf fixed the betas are well determined by the points,
best by dark ones, whose colour is almost pure backscatter.

Why it exists: jointly learning the medium and the Gaussians from the constant beta_prior lets the
Gaussians' colours (initialised from underwater points) absorb the water first, and the photometric loss
is then almost flat along the valley of (colour, medium) pairs that explain the images equally well; the
medium stays near where it started. Starting from this fit, and from de-hazed point colours, puts the
model in the right valley (measurements in README, "UW-3DGS on the synthetic scene").

Occlusions and points that are outliers give wrong observations; an L1 fit shrugs most of them off.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch
from torch import Tensor

from uw3dgs.cameras import Camera


@dataclass
class MediumEstimate:
    beta_d: Tensor
    """[3] per dataset unit."""
    beta_b: Tensor
    """[3] per dataset unit."""
    b_inf: Tensor
    """[3]"""
    clean_colors: Tensor
    """[P, 3] J_p of every input point, de-hazed with the fitted medium (see `estimate_medium`)."""
    fitted_points: int
    """Points with at least `min_views` observations (the only ones that constrain the medium)."""


def _project(points: Tensor, cam: Camera) -> tuple[Tensor, Tensor, Tensor]:
    """Indices of the `points` [P, 3] that land in `cam`'s image in front of it, and their pixel rows, columns."""
    viewmat, K = cam.viewmat.to(points.dtype), cam.K.to(points.dtype)
    p_cam = points @ viewmat[:3, :3].T + viewmat[:3, 3]
    z = p_cam[:, 2]
    uv = (p_cam[:, :2] / z.clamp_min(1e-6)[:, None]) @ K[:2, :2].T + K[:2, 2]
    col, row = uv[:, 0].floor().long(), uv[:, 1].floor().long()
    inside = (z > 1e-6) & (col >= 0) & (col < cam.width) & (row >= 0) & (row < cam.height)
    ids = torch.nonzero(inside).squeeze(1)
    return ids, row[ids], col[ids]


def observe_points(points: Tensor, cameras: list[Camera], images: list[Tensor]) -> tuple[Tensor, Tensor, Tensor]:
    """Pixel colours and ranges of `points` [P, 3] in every view that sees them in front of the camera.

    Returns (point index [M], colour [M, 3], range [M] in world units); nearest-pixel reads, no occlusion test.
    """
    index, colors, ranges = [], [], []
    for cam, image in zip(cameras, images, strict=True):
        ids, row, col = _project(points, cam)
        index.append(ids)
        colors.append(image[row, col].to(points.dtype))
        ranges.append((points[ids] - cam.center.to(points.dtype)).norm(dim=-1))
    return torch.cat(index), torch.cat(colors), torch.cat(ranges)


def open_water_color(points: Tensor, cameras: list[Camera], images: list[Tensor], cells: int,
                     min_share: float) -> Tensor | None:
    """B_inf read off open water: the per-channel median colour of the image regions no initial point lands in.

    Each view is cut into square cells, `cells` across its width. A cell that none of the `points` [P, 3]
    projects into holds nothing SfM could match in any view: open water, whose colour is the veiling light
    B_inf alone (the median shrugs off the odd textureless patch of seabed). It is the only direct view of
    B_inf: from surface points alone B_inf and beta_B trade off along a flat valley (README). None when the
    empty cells hold less than `min_share` of all pixels (no open water in view).
    """
    water, total = [], 0
    for cam, image in zip(cameras, images, strict=True):
        _, row, col = _project(points, cam)
        size = max(1, cam.width // cells)
        grid_w = -(-cam.width // size)
        hit = torch.zeros(-(-cam.height // size) * grid_w, dtype=torch.bool)
        hit[(row // size) * grid_w + col // size] = True
        empty = (~hit).view(-1, grid_w).repeat_interleave(size, 0).repeat_interleave(size, 1)
        water.append(image[empty[:cam.height, :cam.width]])
        total += cam.width * cam.height
    pixels = torch.cat(water)
    if len(pixels) < min_share * total:
        return None
    return pixels.float().median(dim=0).values


def color_ranges(points: Tensor, cameras: list[Camera]) -> Tensor:
    """The range [P] each point's SfM colour was seen at: its mean distance to the `cameras` whose image it lands
    in (where COLMAP could have matched it), or to the nearest camera where it lands in none (an outlier)."""
    total, count = torch.zeros(len(points), dtype=points.dtype), torch.zeros(len(points), dtype=points.dtype)
    for cam in cameras:
        ids = _project(points, cam)[0]
        total[ids] += (points[ids] - cam.center.to(points.dtype)).norm(dim=-1)
        count[ids] += 1
    centers = torch.stack([cam.center.to(points) for cam in cameras])
    nearest = torch.cdist(points, centers).min(dim=1).values
    return torch.where(count > 0, total / count.clamp_min(1), nearest)


def estimate_medium(points: Tensor, point_colors: Tensor, cameras: list[Camera], images: list[Tensor],
                    dataset_scale: float, b_inf: Tensor | None = None, min_views: int = 3,
                    iterations: int = 2000, sfm_cameras: list[Camera] | None = None) -> MediumEstimate:
    """Fit a homogeneous medium and per-point clean colours to the points' observations (see module doc).

    Ranges are converted to dataset units (x `dataset_scale`), so the betas are per dataset unit. Only points
    seen by `min_views` or more views constrain the medium; every point's colour is then de-hazed with it:
    from its own observations (least squares), or, for a point no training view sees (SfM also matches test
    views), its input colour at the range it was seen from (`color_ranges` over `sfm_cameras`, the cameras of
    all the views SfM matched; the training `cameras` when None). A colour left underwater would carry the
    water twice once the model adds it. `b_inf` [3], when given (read off open water by `open_water_color`),
    is kept and only the betas are fitted.
    """
    points = points.float()
    idx, obs, ranges = observe_points(points, cameras, images)
    keep = torch.bincount(idx, minlength=len(points))[idx] >= min_views
    if not bool(keep.any()):
        raise ValueError(f"no initial point is seen by {min_views} or more training views, so the medium cannot be "
                         "estimated from them: use --model.medium.init prior")
    fitted, local = torch.unique(idx[keep], return_inverse=True)
    medium = fit_medium(local, obs[keep].float(), ranges[keep] * dataset_scale, b_inf, iterations)
    seen_at = color_ranges(points, cameras if sfm_cameras is None else sfm_cameras) * dataset_scale
    colors = clean_colors(torch.arange(len(points)), point_colors.detach().float(), seen_at, *medium)
    observed, local = torch.unique(idx, return_inverse=True)
    colors[observed] = clean_colors(local, obs.float(), ranges * dataset_scale, *medium)
    return MediumEstimate(*medium, colors, len(fitted))


def clean_colors(point: Tensor, color: Tensor, z: Tensor, beta_d: Tensor, beta_b: Tensor,
                 b_inf: Tensor) -> Tensor:
    """Least-squares clean colours [P, 3] in [0, 1] of points seen as color [M, 3] at ranges z [M] through a
    homogeneous medium; point [M] in 0..P-1 (every value present)."""
    num_points = int(point.max()) + 1
    return torch.stack([_profiled_residual(point, color[:, c], z.float(), beta_d[c], beta_b[c], b_inf[c],
                                           num_points)[1] for c in range(3)], dim=-1)


def _profiled_residual(point: Tensor, color: Tensor, z: Tensor, beta_d: Tensor, beta_b: Tensor, b_inf: Tensor,
                       num_points: int) -> tuple[Tensor, Tensor]:
    """Residuals [..., M] of the best clean colours for a medium, and those colours [..., P].

    One channel; the medium tensors share any leading shape (candidates). For a given medium each J_p has a
    closed form, least squares over its observations clamped to [0, 1], so only the medium is searched.
    """
    direct = torch.exp(-beta_d[..., None] * z)
    back = b_inf[..., None] * (1 - torch.exp(-beta_b[..., None] * z))
    shape = (*direct.shape[:-1], num_points)
    num = torch.zeros(shape).index_add_(-1, point, direct * (color - back))
    den = torch.zeros(shape).index_add_(-1, point, direct * direct)
    clean = (num / den.clamp_min(1e-12)).clamp(0, 1)
    return clean[..., point] * direct + back - color, clean


def _grid_start(point: Tensor, color: Tensor, z: Tensor, num_points: int, steps: int,
                b_inf: float | None) -> tuple[float, float, float]:
    """The best (beta_D, beta_B, B_inf) of one channel on a coarse grid: a global start for the refinement.

    The L1 landscape has long flat valleys (B_inf against beta_B where backscatter is faint), so a local
    method started at an arbitrary prior can stall in the wrong one. Betas span optical depths 0.02 to 5
    at the median range, whatever the dataset's units. A given `b_inf` is not searched.
    """
    scale = float(z.median())
    betas = torch.logspace(math.log10(0.02), math.log10(5.0), steps) / scale
    veils = torch.linspace(0.02, 0.98, steps) if b_inf is None else torch.tensor([b_inf])
    bd, bb, b = torch.meshgrid(betas, betas, veils, indexing="ij")
    bd, bb, b = bd.reshape(-1), bb.reshape(-1), b.reshape(-1)
    losses = torch.cat([_profiled_residual(point, color, z, bd[i:i + 256], bb[i:i + 256], b[i:i + 256],
                                           num_points)[0].abs().mean(-1) for i in range(0, len(bd), 256)])
    best = int(losses.argmin())
    return float(bd[best]), float(bb[best]), float(b[best])


def fit_medium(point: Tensor, color: Tensor, z: Tensor, b_inf: Tensor | None = None, iterations: int = 2000,
               lr: float = 0.02, grid_steps: int = 16, grid_observations: int = 4096,
               fit_observations: int = 50_000) -> tuple[Tensor, Tensor, Tensor]:
    """L1 fit of color[m] = J[point[m]] exp(-beta_D z[m]) + B_inf (1 - exp(-beta_B z[m])), per channel.

    point [M] in 0..P-1 (every value present), color [M, 3], z [M] > 0; `b_inf` [3] fixes the veiling light
    (read off open water) instead of fitting it. Returns beta_D, beta_B, B_inf [3] (`clean_colors` gives the
    J_p for them). Each channel is independent: a coarse grid search on a random `grid_observations` of the
    observations, then Adam on `fit_observations` of them (so big SfM models cost no more than small ones),
    with the J_p profiled out. L1 tolerates occluded or outlying observations.
    """
    z = z.float()
    order = torch.randperm(len(point), generator=torch.Generator().manual_seed(0))

    def sample(count: int) -> tuple[Tensor, Tensor, int]:  # (observations, their re-numbered points, #points)
        subset = order[:count]
        points, local = torch.unique(point[subset], return_inverse=True)
        return subset, local, len(points)

    grid, grid_local, grid_points = sample(grid_observations)
    fit, fit_local, fit_points = sample(fit_observations)
    results = []
    for c in range(3):
        fixed = None if b_inf is None else float(b_inf[c])
        start = _grid_start(grid_local, color[grid, c].float(), z[grid], grid_points, grid_steps, fixed)
        logs = [math.log(start[0]), math.log(start[1])]  # log beta_D, log beta_B and, unless fixed, logit B_inf
        if fixed is None:
            logs.append(math.log(start[2] / (1 - start[2])))
        params = torch.tensor(logs, requires_grad=True)

        def medium(params: Tensor = params, fixed: float | None = fixed) -> tuple[Tensor, Tensor, Tensor]:
            veil = torch.sigmoid(params[2]) if fixed is None else torch.tensor(fixed)
            return params[0].exp(), params[1].exp(), veil

        optimizer = torch.optim.Adam([params], lr=lr)
        # decay to lr / 100: Adam at a constant rate hovers around an L1 minimum instead of settling in it
        schedule = torch.optim.lr_scheduler.ExponentialLR(optimizer, gamma=0.01 ** (1 / max(iterations, 1)))
        for _ in range(iterations):
            optimizer.zero_grad()
            _profiled_residual(fit_local, color[fit, c].float(), z[fit], *medium(),
                               fit_points)[0].abs().mean().backward()
            optimizer.step()
            schedule.step()
        with torch.no_grad():
            results.append(medium())
    beta_d, beta_b, b_inf = (torch.stack(x, dim=-1) for x in zip(*results, strict=True))
    return beta_d, beta_b, b_inf
