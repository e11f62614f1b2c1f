"""A homogeneous medium read off how each surface point's colour changes with its range across the training views.

A 3D survey sees each seabed point from several cameras at different ranges z_k; its observed colours follow
    I_k = J exp(-beta_D z_k) + B_inf (1 - exp(-beta_B z_k))
with J the point's water-free colour. Traced over a point's ranges this curve pins beta_D, beta_B and B_inf without
the single-image estimate's assumptions (open water in view, near-black surfaces: fields/medium_estimate.py),
provided the ranges differ enough: over a narrow span the direct and backscatter terms trade off and the fit cannot
tell them apart, which the bootstrap spread shows.

- `visible_observations`: every point reprojected into every view in front of it, kept where no other point lies
  clearly nearer along the same few pixels (a depth test against the points themselves), with its colour and
  range (distance from the camera centre, as uw3dgs/medium/formation.py uses it).
- `fit_multiview`: beta_D, beta_B, B_inf per channel and one J per point, fitted jointly by Levenberg-Marquardt
  (float64, the per-point colours eliminated in closed form by the Schur complement, so a step costs O(M) for M
  observations) under a robust Cauchy loss (iteratively reweighted), each point weighted by how wide its range
  span is. The start is a grid over (beta_D, beta_B) with J and B_inf solved by weighted least squares.
- `multiview_estimate`: the above with a bootstrap over points and a verdict per parameter and channel:
  identified by range diversity when enough points span a range ratio of at least `identify_span_ratio`, the
  median point at least `identify_median_span_ratio`, the bootstrap half-spread is within `tolerance` of the value
  and a drift of the surfaces' colours with range (`color_drift`) would move it by at most that, else not
  identified, with the reason.

Its combination with the single-image estimate by evidence is fields/medium_evidence.py.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass, field
from typing import TYPE_CHECKING, Literal

import torch
from torch import Tensor

from uw3dgs.cameras import Camera
from uw3dgs.fields.medium_identifiability import bootstrap_observations, principal_axes
from uw3dgs.options import CheckedConfig, OptionError, check_number

if TYPE_CHECKING:
    from uw3dgs.fields.medium_varying import VaryingEstimate

CHANNELS = "RGB"
PARAMETERS = ("beta_D", "beta_B", "B_inf")
CAUCHY_EFFICIENCY = 2.385
"""The Cauchy loss's scale in units of the noise's standard deviation that gives 95% efficiency on Gaussian noise."""
BLUR_LEVELS = (0.0, 0.25, 0.5, 0.75, 1.0, 1.5, 2.0, 3.0)
"""Gaussian blurs (pixels) `visible_observations` reads colours off, to match a nearer view's footprint to a farther
one's (the nearest level to the wanted blur; 3 pixels is a range ratio of 10)."""
MAD_TO_STD = 1.4826
"""Median absolute deviation to standard deviation, for Gaussian noise."""


@dataclass(frozen=True)
class MultiviewConfig(CheckedConfig):
    """Knobs of the multi-view medium estimate (`multiview_estimate`)."""

    min_views: int = 2
    """Least views a point must be seen in to enter the fit."""
    min_span_ratio: float = 1.1
    """Least ratio of a point's largest to smallest range for it to enter the fit: a point seen at one range says
    nothing about the medium (its J absorbs everything) and only costs time."""
    full_weight_span_ratio: float = 2.0
    """A point's weight is log(span ratio) / log(this), capped at 1: points seen over a wide span weigh most
    (their curve shows the medium; a narrow one mostly its noise and the surfaces' view-dependent colour)."""
    identify_span_ratio: float = 1.5
    """A parameter can only be identified by range diversity when at least `min_span_points` points span a range
    ratio of at least this."""
    min_span_points: int = 30
    """See `identify_span_ratio`."""
    identify_median_span_ratio: float = 2.0
    """A parameter can only be identified by range diversity when the median fitted point spans at least this
    range ratio. On the built-in scene's forward pass (median 1.6) every other check passed a parameter 21-28% off
    (a bias neither the bootstrap nor a colour drift shows); over two or three passes (2.35-3) every parameter was
    within 4% (docs/medium-estimate.md)."""
    tolerance: float = 0.15
    """Identified when the bootstrap half-spread (5-95%) is at most this share of the value."""
    resamples: int = 12
    """Bootstrap fits (points resampled with replacement, each with all its observations)."""
    seed: int = 0
    """Seed of the bootstrap's resampling and of the observation subsets."""
    loss: Literal["cauchy", "huber", "l2"] = "cauchy"
    """Robust loss of the residuals (outlier points, occlusions the depth test missed, glints)."""
    loss_scale: float = 0.0
    """The robust loss's scale (colour units); 0: from the starting fit's residuals (their median absolute
    deviation, scaled for 95% efficiency under Gaussian noise), at least `min_loss_scale`."""
    min_loss_scale: float = 1 / 255
    """The smallest automatic loss scale: one grey level of 8-bit images."""
    max_iterations: int = 100
    """Levenberg-Marquardt iterations per fit."""
    grid_steps: int = 24
    """Starting grid: this many log-spaced candidates for beta_D and for beta_B (optical depths 0.01-10 at the
    median range)."""
    max_grid_observations: int = 10_000
    """Observations (a random subset of whole points) in the starting grid search (each bootstrap refit draws its
    own)."""
    max_observations: int = 30_000
    """Observations (a random subset of whole points) in the fit and each bootstrap refit."""
    color_drift: float = 0.06
    """A relative change of the surfaces' colours over a point's ranges that is not the water's (texture blurring,
    shading, SfM noise landing on neighbouring texture): beta_D read over a point's span of tau optical depths moves
    by about color_drift / tau, so beta_D is not identified where that exceeds `tolerance` at the median point (the
    single-image report's `color_drift`). The fit is also refitted with every point's direct signal drifted by
    +-color_drift over its ranges: a parameter that moves by more than `tolerance` is not identified (the bootstrap
    measures the noise, this the bias such a drift would put in)."""
    spatial_tolerance: float = 0.3
    """The betas vary in space when beta_D fitted to two halves of the points (split at the median along either of
    their two main axes, B_inf held at the whole fit's) differs by more than this share of the whole fit's and by more
    than twice its bootstrap half-spread, in at least `spatial_min_channels` channels (the single-image report's
    rule, fields/medium_identifiability.py)."""
    spatial_min_channels: int = 2
    """See `spatial_tolerance`."""
    depth_cell: int = 4
    """Depth test: a point is visible in a view unless another point projects within the same cell of this many
    pixels and lies nearer by more than `depth_tolerance` of its range. 0 turns the test off."""
    depth_tolerance: float = 0.1
    """See `depth_cell`: relative range margin (SfM noise, sloping surfaces within a cell)."""
    match_footprint: bool = True
    """Read each view's colour off the image blurred to about the surface patch the point's farthest view's pixel
    covers (`visible_observations`); False: nearest-pixel reads."""
    field_nodes: int = 7
    """Where the halves disagree (the medium varies in space), the betas are fitted as a field: a factor on a grid of
    this many nodes along each of the points' two main axes, at evenly spaced quantiles of the points
    (fields/medium_varying.py). 0: no field fit (the betas are then not identified, as before)."""
    field_resamples: int = 6
    """Bootstrap refits of the field fit (each from the whole fit)."""
    field_samples: int = 8
    """Samples along each observation's ray for the field's mean over the path (midpoint rule)."""
    field_smoothness: float = 0.01
    """Weight of the squared differences of neighbouring nodes' log factors, per pair of nodes, in units of the
    robust cost of the observations per node at the loss scale: it fills nodes no ray crosses."""

    def check_options(self) -> None:
        super().check_options()
        check_number(self, "min_views", ge=2, integer=True)
        for name in ("min_span_ratio", "identify_span_ratio"):
            check_number(self, name, ge=1)
        check_number(self, "identify_median_span_ratio", ge=1)
        check_number(self, "full_weight_span_ratio", gt=1)
        for name in ("min_span_points", "resamples", "max_iterations", "grid_steps", "max_grid_observations",
                     "max_observations"):
            check_number(self, name, ge=1, integer=True)
        check_number(self, "seed", ge=0, integer=True)
        check_number(self, "depth_cell", ge=0, integer=True)
        check_number(self, "field_nodes", ge=0, integer=True)
        if self.field_nodes == 1:
            raise OptionError("field_nodes", "must be 0 (no field fit) or at least 2")
        check_number(self, "field_samples", ge=1, integer=True)
        check_number(self, "field_resamples", ge=1, integer=True)
        check_number(self, "field_smoothness", ge=0)
        check_number(self, "spatial_tolerance", ge=0)
        check_number(self, "spatial_min_channels", ge=1, le=3, integer=True)
        for name in ("tolerance", "loss_scale", "depth_tolerance", "color_drift"):
            check_number(self, name, ge=0)
        check_number(self, "min_loss_scale", gt=0)
        if self.loss not in ("cauchy", "huber", "l2"):
            raise OptionError("loss", f"must be one of cauchy, huber, l2, got {self.loss!r}")


# ------------------------------------------------------------------------------------------------ observations

def visible_observations(points: Tensor, cameras: list[Camera], images: list[Tensor], depth_cell: int = 4,
                         depth_tolerance: float = 0.1, match_footprint: bool = True, with_views: bool = False
                         ) -> tuple[Tensor, ...]:
    """Colours and ranges of `points` [P, 3] (world units) in every view where they land in the image in front of
    the camera and pass the depth test: no other point projecting into the same `depth_cell` x `depth_cell` pixel
    cell lies nearer than range / (1 + `depth_tolerance`) (0: no test). Returns (point index [M], colour [M, 3],
    range [M] in world units: the distance from the camera centre), and with `with_views` the view index [M].

    With `match_footprint` a view's colour is read off the image blurred to the surface patch the point's farthest
    view's pixel covers: a pixel is a box of 1 pixel (variance 1/12), the farthest view's pixel is z_max / z of this
    view's pixels across, so the blur is a Gaussian of variance ((z_max / z)^2 - 1) / 12 pixels^2 (the nearest of
    `BLUR_LEVELS`). Read off single pixels, a textured surface's colours regress towards the local mean with range (a
    far pixel averages more texture), which a fit reads as water: more attenuation and backscatter.
    Without it, nearest-pixel reads."""
    points = points.double()
    seen = []
    for k, cam in enumerate(cameras):
        uv, inside = cam.project(points)
        ids = torch.nonzero(inside).squeeze(1)
        col, row = uv[ids].floor().long().unbind(-1)
        z = (points[ids] - cam.center.double()).norm(dim=-1)
        if depth_cell > 0 and len(ids):
            grid_w = -(-cam.width // depth_cell)
            cell = (row // depth_cell) * grid_w + col // depth_cell
            nearest = torch.full((int(cell.max()) + 1,), math.inf, dtype=torch.float64).scatter_reduce(
                0, cell, z, "amin")
            keep = z <= nearest[cell] * (1 + depth_tolerance)
            ids, row, col, z = ids[keep], row[keep], col[keep], z[keep]
        seen.append((k, ids, row, col, z))
    index, ranges = torch.cat([s[1] for s in seen]), torch.cat([s[4] for s in seen])
    farthest = torch.zeros(len(points), dtype=torch.float64).scatter_reduce(0, index, ranges, "amax")
    colors = []
    for k, ids, row, col, z in seen:
        image = images[k].double()
        if not match_footprint:
            colors.append(image[row, col])
            continue
        sigma = (((farthest[ids] / z).square() - 1).clamp_min(0) / 12).sqrt()
        level = (sigma[:, None] - torch.tensor(BLUR_LEVELS, dtype=torch.float64)).abs().argmin(-1)
        color = torch.empty(len(ids), 3, dtype=torch.float64)
        for j in torch.unique(level).tolist():
            pick = level == j
            color[pick] = _blurred(image, BLUR_LEVELS[j])[row[pick], col[pick]]
        colors.append(color)
    if with_views:
        views = torch.cat([torch.full((len(s[1]),), s[0], dtype=torch.long) for s in seen])
        return index, torch.cat(colors), ranges, views
    return index, torch.cat(colors), ranges


def _blurred(image: Tensor, sigma: float) -> Tensor:
    """`image` [H, W, 3] convolved with a Gaussian of `sigma` pixels (separable, edges replicated)."""
    if sigma <= 0:
        return image
    radius = max(1, math.ceil(3 * sigma))
    x = torch.arange(-radius, radius + 1, dtype=torch.float64)
    kernel = torch.exp(-0.5 * (x / sigma).square())
    kernel = (kernel / kernel.sum()).to(image.dtype)
    out = image.permute(2, 0, 1)[:, None]  # [3, 1, H, W]
    out = torch.nn.functional.pad(out, (radius, radius, 0, 0), mode="replicate")
    out = torch.nn.functional.conv2d(out, kernel.view(1, 1, 1, -1))
    out = torch.nn.functional.pad(out, (0, 0, radius, radius), mode="replicate")
    out = torch.nn.functional.conv2d(out, kernel.view(1, 1, -1, 1))
    return out[:, 0].permute(1, 2, 0)


def range_bounds(point: Tensor, z: Tensor, num_points: int) -> tuple[Tensor, Tensor]:
    """Per point (ids `point` [M] in 0..num_points-1, ranges z [M] > 0): its nearest and farthest range [P], float64
    (inf and 0 for a point never seen)."""
    lo = torch.full((num_points,), math.inf, dtype=torch.float64).scatter_reduce(0, point, z.double(), "amin")
    hi = torch.zeros(num_points, dtype=torch.float64).scatter_reduce(0, point, z.double(), "amax")
    return lo, hi


def point_spans(point: Tensor, z: Tensor, num_points: int) -> tuple[Tensor, Tensor]:
    """Per point (ids `point` [M] in 0..num_points-1, ranges z [M] > 0): (views [P], largest / smallest range [P];
    1 for a point seen once, 0 for one never seen)."""
    count = torch.bincount(point, minlength=num_points)
    lo, hi = range_bounds(point, z, num_points)
    return count, torch.where(count > 0, hi / lo, torch.zeros_like(hi))


def span_weights(ratio: Tensor, full_weight_span_ratio: float) -> Tensor:
    """A point's weight from its range span ratio [P] >= 1: log(ratio) / log(full_weight_span_ratio), capped at 1."""
    return (ratio.clamp_min(1.0).log() / math.log(full_weight_span_ratio)).clamp(0.0, 1.0)


# ------------------------------------------------------------------------------------------------ the fit

@dataclass
class MultiviewFit:
    """A homogeneous medium fitted jointly with a colour per point (`fit_multiview`)."""

    beta_d: Tensor
    """[3] per unit of the ranges given."""
    beta_b: Tensor
    """[3]"""
    b_inf: Tensor
    """[3]"""
    clean: Tensor
    """[P, 3] the points' fitted water-free colours J (unconstrained: noise can push a dark one below 0)."""
    loss_scale: Tensor
    """[3] the robust loss's scale used per channel (colour units)."""
    iterations: int
    """Levenberg-Marquardt iterations run."""
    cost: Tensor
    """[3] the weighted robust cost at the fit per channel (float64, at `loss_scale`)."""

    @property
    def medium(self) -> tuple[Tensor, Tensor, Tensor]:
        return self.beta_d, self.beta_b, self.b_inf

    @property
    def matrix(self) -> Tensor:
        """[3 parameters (beta_D, beta_B, B_inf), 3 channels] float64."""
        return torch.stack([t.double() for t in self.medium])


def _robust(r: Tensor, scale: Tensor, loss: str) -> tuple[Tensor, Tensor]:
    """(loss rho(r), IRLS weight rho'(r) / r) of residuals r [C, M] with per-channel scale [C, 1]."""
    if loss == "l2":
        return 0.5 * r * r, torch.ones_like(r)
    u = r / scale
    if loss == "huber":
        a = u.abs()
        rho = torch.where(a <= 1, 0.5 * r * r, scale * scale * (a - 0.5))
        return rho, torch.where(a <= 1, torch.ones_like(r), 1 / a.clamp_min(1e-12))
    return 0.5 * scale * scale * torch.log1p(u * u), 1 / (1 + u * u)


def _model(theta: Tensor, clean: Tensor, point: Tensor, z: Tensor) -> tuple[Tensor, Tensor, Tensor]:
    """Predicted colours [C, M] and their derivatives for theta [C, 3] = log(beta_D, beta_B, B_inf) and clean
    colours [C, P]: (prediction, d/dJ [C, M], d/dtheta [C, M, 3])."""
    beta_d, beta_b, b_inf = theta.exp().unbind(-1)
    direct = torch.exp(-beta_d[:, None] * z)
    veiled = torch.exp(-beta_b[:, None] * z)
    j = clean[:, point]
    grad = torch.stack([-j * z * beta_d[:, None] * direct, b_inf[:, None] * z * beta_b[:, None] * veiled,
                        b_inf[:, None] * (1 - veiled)], dim=-1)
    return j * direct + b_inf[:, None] * (1 - veiled), direct, grad


def _cost(theta: Tensor, clean: Tensor, point: Tensor, z: Tensor, color: Tensor, weight: Tensor, scale: Tensor,
          loss: str) -> Tensor:
    """[C] the weighted robust cost."""
    return (weight * _robust(_model(theta, clean, point, z)[0] - color, scale, loss)[0]).sum(-1)


def _profiled_start(point: Tensor, z: Tensor, color: Tensor, weight: Tensor, num_points: int, steps: int,
                    b_inf: Tensor | None) -> tuple[Tensor, Tensor]:
    """The starting medium: a grid over (beta_D, beta_B), each candidate with the clean colours and B_inf (unless
    `b_inf` [C] holds it; NaN entries are free) solved by weighted least squares. Returns theta [C, 3], clean
    colours [C, P]."""
    betas = torch.logspace(-2, 1, steps, dtype=torch.float64) / float(z.median())
    bd, bb = torch.meshgrid(betas, betas, indexing="ij")
    bd, bb = bd.reshape(-1), bb.reshape(-1)
    best_sse = torch.full((color.shape[0],), math.inf, dtype=torch.float64)
    best = torch.zeros(color.shape[0], 3, dtype=torch.float64)
    for chunk in torch.arange(len(bd)).split(64):
        a = torch.exp(-bd[chunk, None] * z)  # [G, M]
        c = 1 - torch.exp(-bb[chunk, None] * z)
        saa = _per_point(weight * a * a, point, num_points)
        sac = _per_point(weight * a * c, point, num_points)
        gamma = (sac / saa.clamp_min(1e-300))[:, point]  # J = alpha - B gamma
        d = c - gamma * a  # [G, M]: the backscatter's column once J is eliminated
        for ch in range(color.shape[0]):
            y = color[ch]
            alpha = (_per_point(weight * a * y, point, num_points) / saa.clamp_min(1e-300))[:, point]
            e = y - alpha * a
            if b_inf is not None and not bool(b_inf[ch].isnan()):
                veil = b_inf[ch].expand(len(chunk))
            else:
                veil = ((weight * d * e).sum(-1) / (weight * d * d).sum(-1).clamp_min(1e-300)).clamp(1e-3, 1.0)
            sse = (weight * (e - veil[:, None] * d).square()).sum(-1)
            k = int(sse.argmin())
            if float(sse[k]) < float(best_sse[ch]):
                best_sse[ch] = sse[k]
                best[ch] = torch.stack([bd[chunk][k], bb[chunk][k], veil[k]])
    theta = best.log()
    return theta, _clean_given(theta, point, z, color, weight, num_points)


def _per_point(values: Tensor, point: Tensor, num_points: int) -> Tensor:
    """Sums of values [..., M] per point: [..., P]."""
    return torch.zeros((*values.shape[:-1], num_points), dtype=values.dtype).index_add_(-1, point, values)


def _clean_given(theta: Tensor, point: Tensor, z: Tensor, color: Tensor, weight: Tensor, num_points: int) -> Tensor:
    """[C, P] the weighted least-squares clean colours for the medium theta [C, 3] (log)."""
    beta_d, beta_b, b_inf = theta.exp().unbind(-1)
    a = torch.exp(-beta_d[:, None] * z)
    back = b_inf[:, None] * (1 - torch.exp(-beta_b[:, None] * z))
    return _per_point(weight * a * (color - back), point, num_points) / \
        _per_point(weight * a * a, point, num_points).clamp_min(1e-300)


def fit_multiview(point: Tensor, color: Tensor, z: Tensor, weight: Tensor | None = None,
                  b_inf: Tensor | None = None, config: MultiviewConfig | None = None,
                  start: tuple[Tensor, Tensor, Tensor] | None = None, loss_scale: Tensor | None = None
                  ) -> MultiviewFit:
    """Fit beta_D, beta_B, B_inf [3] and clean colours J [P, 3] to observations color [M, 3] of points
    point [M] (ids 0..P-1, every id present) at ranges z [M] > 0, minimising the weighted robust loss of
    J_p exp(-beta_D z) + B_inf (1 - exp(-beta_B z)) - I. `weight` [M] (default 1) weighs each observation; `b_inf`
    [3] holds B_inf where it is not NaN. `start` (beta_D, beta_B, B_inf) skips the grid search (to refine a known
    medium); `loss_scale` [3] replaces the automatic scale. Float64 throughout; the betas
    are per unit of z."""
    config = config or MultiviewConfig()
    point, z = point.long(), z.double()
    color = color.double().T.contiguous()  # [C, M]
    weight = torch.ones_like(z) if weight is None else weight.double()
    num_points = int(point.max()) + 1
    held = torch.zeros(3, dtype=torch.bool) if b_inf is None else ~b_inf.double().isnan()
    if start is None:
        sub = _subset(point, num_points, config.max_grid_observations, config.seed)
        ids, local = torch.unique(point[sub], return_inverse=True)
        theta, _ = _profiled_start(local, z[sub], color[:, sub], weight[sub], len(ids), config.grid_steps,
                                   None if b_inf is None else b_inf.double())
    else:
        theta = torch.stack([s.double() for s in start], dim=-1).clamp_min(1e-6).log()
    if b_inf is not None:
        theta[held, 2] = b_inf.double()[held].clamp_min(1e-6).log()
    clean = _clean_given(theta, point, z, color, weight, num_points)
    free = torch.ones(3, 3, dtype=torch.float64)
    free[held, 2] = 0.0
    data = (point, z, color, weight, num_points, free, config)
    if loss_scale is not None:
        scale = loss_scale.double()
        theta, clean, iterations = _levenberg_marquardt(theta, clean, scale, *data)
    else:  # the scale from the residuals, again once the fit has left the outliers' pull (at most 3 rounds)
        scale, iterations = None, 0
        for _ in range(3):
            new_scale = _auto_scale(theta, clean, point, z, color, config)
            if scale is not None and bool(((new_scale - scale).abs() <= 0.1 * scale).all()):
                break
            scale = new_scale
            theta, clean, steps = _levenberg_marquardt(theta, clean, scale, *data)
            iterations += steps
    beta_d, beta_b, veil = theta.exp().float().unbind(-1)
    cost = _cost(theta, clean, point, z, color, weight, scale[:, None], config.loss)
    return MultiviewFit(beta_d, beta_b, veil, clean.T.float(), scale.float(), iterations, cost)


def _auto_scale(theta: Tensor, clean: Tensor, point: Tensor, z: Tensor, color: Tensor, config: MultiviewConfig
                ) -> Tensor:
    """[3] the robust loss's scale: `config.loss_scale`, or from the residuals' median absolute deviation (scaled
    for 95% efficiency under Gaussian noise), at least `min_loss_scale`."""
    if config.loss_scale > 0:
        return torch.full((3,), config.loss_scale, dtype=torch.float64)
    residual = _model(theta, clean, point, z)[0] - color
    mad = (residual - residual.median(-1, keepdim=True).values).abs().median(-1).values
    return (CAUCHY_EFFICIENCY * MAD_TO_STD * mad).clamp_min(config.min_loss_scale)


def _levenberg_marquardt(theta: Tensor, clean: Tensor, loss_scale: Tensor, point: Tensor, z: Tensor, color: Tensor,
                         weight: Tensor, num_points: int, free: Tensor, config: MultiviewConfig
                         ) -> tuple[Tensor, Tensor, int]:
    """Minimise the weighted robust cost over theta [C, 3] (log medium; `free` [C, 3] 0 where held) and the clean
    colours [C, P], from the given ones: Levenberg-Marquardt on the IRLS-weighted Gauss-Newton system, the clean
    colours eliminated per point (Schur complement; each observation depends on one). Returns theta, clean, the
    iterations run."""
    scale = loss_scale[:, None]
    damping = torch.full((theta.shape[0],), 1e-3, dtype=torch.float64)
    cost = _cost(theta, clean, point, z, color, weight, scale, config.loss)
    iterations = 0
    while iterations < config.max_iterations:
        iterations += 1
        pred, dj, dt = _model(theta, clean, point, z)
        r = pred - color
        w = weight * _robust(r, scale, config.loss)[1]
        dt = dt * free[:, None, :]
        hjj = _per_point(w * dj * dj, point, num_points)  # [C, P]
        hjt = _per_point((w * dj)[:, None, :] * dt.transpose(-1, -2), point, num_points)  # [C, 3, P]
        htt = torch.einsum("cm,cmi,cmj->cij", w, dt, dt)
        gj = _per_point(w * dj * r, point, num_points)
        gt = torch.einsum("cm,cmi->ci", w, dt * r[..., None])
        hjj_d = (hjj * (1 + damping[:, None])).clamp_min(1e-300)
        htt_d = htt + damping[:, None, None] * torch.diag_embed(torch.diagonal(htt, dim1=-2, dim2=-1)) \
            + torch.diag_embed(1 - free)  # a held parameter: a unit row, zero right-hand side
        schur = htt_d - torch.einsum("cip,cjp->cij", hjt / hjj_d[:, None], hjt)
        rhs = gt - torch.einsum("cip,cp->ci", hjt, gj / hjj_d)
        step_t = -torch.linalg.solve(schur + 1e-12 * torch.eye(3, dtype=torch.float64), rhs) * free
        step_j = -(gj + torch.einsum("cip,ci->cp", hjt, step_t)) / hjj_d
        new_theta = theta + step_t.clamp(-2.0, 2.0)
        new_clean = clean + step_j
        new_cost = _cost(new_theta, new_clean, point, z, color, weight, scale, config.loss)
        better = new_cost < cost
        theta = torch.where(better[:, None], new_theta, theta)
        clean = torch.where(better[:, None], new_clean, clean)
        gain = (cost - torch.where(better, new_cost, cost)) / cost.clamp_min(1e-300)
        cost = torch.where(better, new_cost, cost)
        damping = torch.where(better, (damping / 3).clamp_min(1e-9), damping * 4)
        converged = (better & ((gain < 1e-10) | (step_t.abs().amax(-1) < 1e-9))) | (damping > 1e8)
        if bool(converged.all()):
            break
    return theta, clean, iterations


def _subset(point: Tensor, num_points: int, max_observations: int, seed: int) -> Tensor:
    """Indices of the observations of a random subset of whole points with at most about `max_observations`
    observations (all of them when there are fewer)."""
    if len(point) <= max_observations:
        return torch.arange(len(point))
    order = torch.randperm(num_points, generator=torch.Generator().manual_seed(seed))
    counts = torch.bincount(point, minlength=num_points)[order]
    chosen = order[: int(torch.searchsorted(torch.cumsum(counts, 0), max_observations)) + 1]
    return torch.nonzero(torch.isin(point, chosen)).squeeze(1)


def _deeper(a: MultiviewFit, b: MultiviewFit) -> Tensor:
    """[3 parameters, 3 channels] per channel the medium of whichever of two fits of the same data has the lower
    cost."""
    return torch.where((b.cost < a.cost)[None], b.matrix, a.matrix)


def _drift_sensitivity(point: Tensor, color: Tensor, z: Tensor, weight: Tensor, b_inf: Tensor | None,
                       whole: MultiviewFit, config: MultiviewConfig) -> Tensor:
    """[3 parameters, 3 channels] the largest relative move of `whole`'s medium when each point's direct signal
    J exp(-beta_D z) drifts by +-`config.color_drift` over its ranges (log-linear in range from its nearest to its
    farthest view, centred), refitted from `whole` at its loss scale: the bias a surface colour that changes with
    range for reasons other than the water (texture blurring, shading, SfM noise) would put into each parameter."""
    point, z = point.long(), z.double()
    lo, hi = (bound.log()[point] for bound in range_bounds(point, z, int(point.max()) + 1))
    place = (z.log() - lo) / (hi - lo).clamp_min(1e-12) - 0.5  # [-0.5, 0.5] across each point's span
    direct = whole.clean[point] * torch.exp(-whole.beta_d.double()[None] * z[:, None])  # [M, 3]
    moved = torch.zeros(3, 3, dtype=torch.float64)
    for sign in (1.0, -1.0):
        drifted = color.double() + torch.expm1(sign * config.color_drift * place)[:, None] * direct
        refit = fit_multiview(point, drifted, z, weight, b_inf, config, start=whole.medium,
                              loss_scale=whole.loss_scale)
        moved = torch.maximum(moved, (refit.matrix - whole.matrix).abs())
    return moved / whole.matrix.abs().clamp_min(1e-9)


def _spatial_disagreement(point: Tensor, color: Tensor, z: Tensor, weight: Tensor, positions: Tensor,
                          whole: MultiviewFit, config: MultiviewConfig) -> list[float] | None:
    """[3] the largest |beta_D of one half - the other's| (per unit of range) over the halves of the points (ids
    `point` [M] into positions [P, 3]) split at the median along each of their two main axes, each half fitted with
    B_inf held at `whole`'s; None where a half has fewer than `min_span_points` points."""
    disagreement = torch.zeros(3, dtype=torch.float64)
    for axis in principal_axes(positions):
        coord = positions @ axis.double()
        side = coord > coord.median()
        betas = []
        for half in (side, ~side):
            rows = half[point]
            ids, local = torch.unique(point[rows], return_inverse=True)
            if len(ids) < config.min_span_points:
                return None
            betas.append(fit_multiview(local, color[rows], z[rows], weight[rows], whole.b_inf, config).beta_d.double())
        disagreement = torch.maximum(disagreement, (betas[0] - betas[1]).abs())
    return disagreement.tolist()


RELATIVE_READABLE = 10.0
"""Relative spreads and differences above this (1,000%) are printed in absolute units: near beta = 0 a ratio says
nothing (a dry scene's beta_D of 1e-7 gave "halves 2907608263% apart")."""


def _relative_or_absolute(relative: float, absolute: float, unit: str = " per unit") -> str:
    """'12%' where the ratio is readable, else '0.0021 per unit' (the absolute value of the same difference; `unit`
    '' for B_inf, a colour)."""
    return f"{relative:.0%}" if relative <= RELATIVE_READABLE else f"{absolute:.2g}{unit}"


# ------------------------------------------------------------------------------------------------ verdicts

def _unit(name: str) -> str:
    return "" if name == "B_inf" else " per unit"


@dataclass
class MultiviewCheck:
    name: str
    """'beta_D', 'beta_B' or 'B_inf'."""
    channel: str
    value: float
    spread: float
    """Half the width of the bootstrap 5-95% interval, relative to the value (0 for a B_inf held)."""
    identified: bool
    reason: str
    """Why not (empty when identified)."""
    half_width: float = 0.0
    """The same half width in the value's units (per unit of range for the betas)."""

    def spread_text(self) -> str:
        """'+-12%', or '+-0.0021 per unit' where the value is so near 0 that the ratio says nothing."""
        return "+-" + _relative_or_absolute(self.spread, self.half_width, _unit(self.name))


@dataclass
class MultiviewEstimate:
    """The multi-view fit with its bootstrap and verdicts (`multiview_estimate`)."""

    fit: MultiviewFit | None
    """None: too few points with a range span to fit anything."""
    points: int
    """Points that entered the fit (seen in `min_views`+ views over a ratio of `min_span_ratio`+)."""
    span_points: int
    """Of those, the points whose range ratio is at least `identify_span_ratio`."""
    span_ratio: tuple[float, float, float]
    """The 10th, 50th and 90th percentile of the fitted points' range ratios (largest / smallest range)."""
    held: list[bool]
    """[3] channels whose B_inf was held (given), not fitted."""
    median_span: float = 0.0
    """The median over the fitted points of their largest less their smallest range (units of the ranges)."""
    spatial_disagreement: list[float] | None = None
    """[3] the largest |beta_D of one half of the points - the other's| / the whole fit's, over the two main axes
    (None: not checked, no positions or too few points in a half)."""
    spatial_difference: list[float] | None = None
    """[3] the same difference in absolute units (per unit of range)."""
    varies_in_space: bool = False
    checks: list[MultiviewCheck] = field(default_factory=list)
    drift: list[list[float]] | None = None
    """[3 parameters][3 channels] the largest relative move of the fit under a +-`color_drift` drift of the
    surfaces' colours over each point's ranges (`_drift_sensitivity`)."""
    upper: list[list[float]] | None = None
    """[3 parameters (beta_D, beta_B, B_inf)][3 channels] the bootstrap's 95% quantile, at least the fit's value:
    an upper bound in absolute units (what the water verdict reads; the relative spreads explode near 0)."""
    varying: VaryingEstimate | None = None
    """Where the medium varies in space and the rays are known: the betas fitted as a field
    (fields/medium_varying.py)."""

    def check(self, name: str, c: int) -> MultiviewCheck:
        return next(x for x in self.checks if x.name == name and x.channel == CHANNELS[c])

    def lines(self) -> list[str]:
        out = []
        for name in PARAMETERS:
            checks = [x for x in self.checks if x.name == name]
            values = ", ".join(f"{x.value:.3f} {x.spread_text()}" for x in checks)
            verdict = "identified by range diversity" if all(x.identified for x in checks) else "; ".join(
                f"{x.channel} not identified: {x.reason}" for x in checks if not x.identified)
            out.append(f"multi-view {name} ({values}): {verdict}")
        if self.spatial_disagreement is not None:
            halves = self.halves_text()
            out.append(f"multi-view: halves of the scene give beta_D {halves} apart: "
                       f"{'varies in space' if self.varies_in_space else 'homogeneous within the tolerance'}")
        if self.varying is not None:
            out += self.varying.lines()
        lo, mid, hi = self.span_ratio
        out.append(f"multi-view: {self.points} points seen over a range span, {self.span_points} of them over a "
                   f"ratio >= its threshold; span ratio {lo:.2f}/{mid:.2f}/{hi:.2f} (10/50/90%), median span "
                   f"{self.median_span:.2f}")
        return out

    def halves_text(self) -> str:
        """The halves' beta_D difference per channel, '12%/8%/5%' (of the whole fit's) or in absolute units."""
        return "/".join(_relative_or_absolute(r, a) for r, a in zip(self.spatial_disagreement or [],
                                                                   self.spatial_difference or [], strict=True))

    def to_json(self) -> dict:
        out = {k: v for k, v in asdict(self).items() if k not in ("fit", "varying")}
        if self.varying is not None:
            out["varying"] = self.varying.to_json()
        if self.fit is not None:
            out["medium"] = {name: t.tolist() for name, t in zip(PARAMETERS, self.fit.medium, strict=True)}
        return out


def observe_and_estimate(points: Tensor, cameras: list[Camera], images: list[Tensor], dataset_scale: float,
                         config: MultiviewConfig | None = None, b_inf: Tensor | None = None) -> MultiviewEstimate:
    """`multiview_estimate` of the `points` [P, 3] (world units) seen in the views (`visible_observations`), the
    betas per dataset unit (ranges x `dataset_scale`)."""
    config = config or MultiviewConfig()
    point, color, z, view = visible_observations(points, cameras, images, config.depth_cell, config.depth_tolerance,
                                                 config.match_footprint, with_views=True)
    origins = torch.stack([cam.center.double() for cam in cameras])[view]
    return multiview_estimate(point, color, z * dataset_scale, config, b_inf, positions=points, origins=origins)


def multiview_estimate(point: Tensor, color: Tensor, z: Tensor, config: MultiviewConfig | None = None,
                       b_inf: Tensor | None = None, positions: Tensor | None = None,
                       origins: Tensor | None = None) -> MultiviewEstimate:
    """The multi-view medium of observations color [M, 3] of points point [M] (any ids) at ranges z [M] (the unit
    of the betas), with a bootstrap over points and a verdict per parameter and channel (module doc). `b_inf` [3]
    holds B_inf where it is not NaN (read off open water, say): those are reported as held, not identified here.
    `positions` [P, 3] (indexed by the ids of `point`) allow the check of a medium that varies across the scene;
    with `origins` [M, 3] too (each observation's camera centre, the positions' units) a medium found varying is
    fitted as a field (`config.field_nodes`, fields/medium_varying.py)."""
    config = config or MultiviewConfig()
    ids, point = torch.unique(point.long(), return_inverse=True)
    count, ratio = point_spans(point, z, len(ids))
    enter = (count >= config.min_views) & (ratio >= config.min_span_ratio)
    rows = enter[point]
    held = [False] * 3 if b_inf is None else (~b_inf.double().isnan()).tolist()
    fitted_ratio = ratio[enter]
    span_points = int((fitted_ratio >= config.identify_span_ratio).sum())
    quantiles = tuple(float(q) for q in torch.quantile(fitted_ratio, torch.tensor([0.1, 0.5, 0.9],
                                                                                  dtype=torch.float64))) \
        if len(fitted_ratio) else (1.0, 1.0, 1.0)
    lo_z, hi_z = range_bounds(point, z, len(ids))
    median_span = float((hi_z - lo_z)[enter].median()) if bool(enter.any()) else 0.0
    result = MultiviewEstimate(None, int(enter.sum()), span_points, quantiles, held, median_span)
    few = f"only {span_points} points span a range ratio >= {config.identify_span_ratio:g} " \
          f"(< {config.min_span_points}); median span ratio {quantiles[1]:.2f}"
    if int(enter.sum()) < 3:
        result.checks = [MultiviewCheck(n, CHANNELS[c], math.nan, math.inf, False, few)
                         for n in PARAMETERS for c in range(3)]
        return result
    local = torch.unique(point[rows], return_inverse=True)[1]
    weights = span_weights(ratio, config.full_weight_span_ratio)[point[rows]]
    obs = (local, color[rows].double(), z[rows].double())
    sub = _subset(local, int(local.max()) + 1, config.max_observations, config.seed)
    sub_ids = torch.unique(local[sub], return_inverse=True)[1]
    fit = fit_multiview(sub_ids, obs[1][sub], obs[2][sub], weights[sub], b_inf, config)
    result.fit = fit
    generator = torch.Generator().manual_seed(config.seed)
    boot = []
    for _ in range(config.resamples):
        new_ids, picked = bootstrap_observations(sub_ids, generator)
        resample = (new_ids, obs[1][sub][picked], obs[2][sub][picked], weights[sub][picked], b_inf, config)
        # the whole fit again, starting grid included: where the resample's cost has a second valley as deep, it
        # shows as spread (a refit started at the fit alone would stay in its valley and report it as pinned); and
        # from the fit: each channel keeps the deeper of the two, so a grid start that stops in a shallower valley
        # of the resample (a local minimum, not what the data prefer) is not read as spread
        cold = fit_multiview(*resample, loss_scale=fit.loss_scale)
        warm = fit_multiview(*resample, start=fit.medium, loss_scale=fit.loss_scale)
        boot.append(_deeper(cold, warm))
    values = fit.matrix  # [3 params, 3 channels]
    if positions is not None:
        where = torch.zeros(int(sub_ids.max()) + 1, 3, dtype=torch.float64)
        where[sub_ids] = positions.double()[ids[point[rows]][sub]]
        difference = _spatial_disagreement(sub_ids, obs[1][sub], obs[2][sub], weights[sub], where, fit, config)
        if difference is not None:
            result.spatial_difference = difference
            result.spatial_disagreement = (torch.tensor(difference, dtype=torch.float64)
                                           / fit.beta_d.double().clamp_min(1e-9)).tolist()
    drift = _drift_sensitivity(sub_ids, obs[1][sub], obs[2][sub], weights[sub], b_inf, fit, config)
    result.drift = drift.tolist()
    lo, hi = torch.quantile(torch.stack(boot), torch.tensor([0.05, 0.95], dtype=torch.float64), dim=0)
    result.upper = torch.maximum(hi, values).tolist()
    half_width = (hi - lo) / 2
    spread = half_width / values.abs().clamp_min(1e-9)
    if result.spatial_disagreement is not None:
        result.varies_in_space = sum(d > config.spatial_tolerance and d > 2 * float(spread[0, c])
                                     for c, d in enumerate(result.spatial_disagreement)) >= config.spatial_min_channels
    if result.varies_in_space and origins is not None and config.field_nodes > 0:
        from uw3dgs.fields.medium_varying import varying_estimate  # it builds on this module's fit

        ends = positions.double()[ids[point[rows]][sub]]
        # B_inf is fitted with the field even where it was given: in water that varies, what looks like open water
        # can be veiled seabed (the survey-gradient variant reads it 5-9% high with no open water in the scene)
        result.varying = varying_estimate(sub_ids, obs[1][sub], obs[2][sub], origins.double()[rows][sub], ends,
                                          weights[sub], fit, positions.double()[ids], None, config)
    checks: dict[tuple[str, int], MultiviewCheck] = {}
    for k, name in reversed(list(enumerate(PARAMETERS))):  # B_inf, beta_B, beta_D: each leans on the ones before
        for c in range(3):
            if name == "B_inf" and held[c]:
                checks[(name, c)] = MultiviewCheck(name, CHANNELS[c], float(values[k, c]), 0.0, False,
                                                   "held at the value given (not fitted here)")
                continue
            why = []
            if span_points < config.min_span_points:
                why.append(few)
            elif quantiles[1] < config.identify_median_span_ratio:
                why.append(f"the median point spans a range ratio of {quantiles[1]:.2f} (< "
                           f"{config.identify_median_span_ratio:g}): too little to separate the water from colours "
                           "that change with range")
            if float(spread[k, c]) > config.tolerance:
                text = _relative_or_absolute(float(spread[k, c]), float(half_width[k, c]), _unit(name))
                why.append(f"bootstrap spread +-{text} (> {config.tolerance:.0%})")
            depth = float(values[0, c]) * median_span  # the median point's span in optical depths of beta_D
            if name == "beta_D" and config.color_drift / max(depth, 1e-9) > config.tolerance:
                moved = _relative_or_absolute(config.color_drift / max(depth, 1e-9),
                                              config.color_drift / max(median_span, 1e-9))
                why.append(f"the median point spans {depth:.2f} optical depths: a {config.color_drift:.0%} drift of "
                           f"the surfaces' colours with range that is not the water's would move it by {moved} "
                           f"(> {config.tolerance:.0%})")
            if float(drift[k, c]) > config.tolerance:
                moved = _relative_or_absolute(float(drift[k, c]), float(drift[k, c] * values[k, c].abs()), _unit(name))
                why.append(f"a {config.color_drift:.0%} drift of the surfaces' colours over each point's ranges that "
                           f"is not the water's moves it by {moved} (> {config.tolerance:.0%})")
            # the backscatter curve is what the direct signal is read after: a channel whose curve is not pinned
            # leaves its beta_D unpinned too, whatever its own bootstrap says (one valley can hold it still)
            leans = {"B_inf": (), "beta_B": ("B_inf",), "beta_D": ("B_inf", "beta_B")}[name]
            weak = [other for other in leans
                    if not (other == "B_inf" and held[c]) and not checks[(other, c)].identified]
            if name != "B_inf" and result.varies_in_space:
                why.append(f"varies in space: the halves of the scene give beta_D {result.halves_text()} apart (> "
                           f"{config.spatial_tolerance:.0%} in {config.spatial_min_channels}+ channels); a homogeneous "
                           "estimate is an average")
            if weak and not why:
                why.append(f"fitted with a {' and '.join(weak)} that is not identified: the backscatter it leaves "
                           "moves with it")
            checks[(name, c)] = MultiviewCheck(name, CHANNELS[c], float(values[k, c]), float(spread[k, c]),
                                               not why, "; ".join(why), float(half_width[k, c]))
    result.checks = [checks[(name, c)] for name in PARAMETERS for c in range(3)]
    return result


