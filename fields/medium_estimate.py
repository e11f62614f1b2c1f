"""A first estimate of a homogeneous medium from the initial (SfM) points, before any Gaussian is trained.

Every initial point p is projected into every training view k that sees it in front of the camera; the
pixel colour there is an observation I_pk of the same surface at range z_pk, and the formation model says
    I_pk = J_p exp(-beta_D z_pk) + B_inf (1 - exp(-beta_B z_pk))
with one unknown clean colour J_p per point. The medium is read off these observations in three steps,
as Sea-thru does (Akkaynak & Treibitz 2019):

1. B_inf off open water (`find_open_water`): image regions no point lands in show the veiling light alone, when
   they look like water (most of them one colour; holes in the points over seabed do not).
2. beta_B off the darkest observations (`dark_pixels`, `fit_backscatter`): in each range bin the darkest
   1% are taken as surfaces with J ~ 0 (shadows, crevices, dark sponges), whose colour is the backscatter
   B_inf (1 - exp(-beta_B z)) alone. Without open water B_inf is fitted to them with beta_B.
3. beta_D from all observations (`fit_attenuation`): how a point's colour changes with range, with each
   J_p solved in closed form for every candidate beta_D.
4. Dark is not black (`fit_backscatter_residual`): real sand and rock reflect 8-12% at their darkest, and read
   as backscatter such surfaces saturate it early (beta_B several times too high). Sea-thru's residual term
   models them: dark(z) = B_inf (1 - exp(-beta_B z)) + J' exp(-beta_D z), J' >= 0 the darkest surfaces' own
   signal, attenuated with the beta_D of step 3 (the same water). Steps 2-3 alternate with it; per channel it
   is kept only where it explains the dark samples better by the Bayesian information criterion (one more
   parameter), so black shadows keep the plain fit. Without open water its far end, where every colour
   converges to the veiling light, gives B_inf.

Without open water (`estimate_from_views`), B_inf comes from the far, veiled end of the ranges before steps 2-3
(`veiling_light_from_far_end`): the middle of the darkest surfaces' plateau and the far observations' median colour.

Why not one joint fit of everything: with J_p free, (B_inf, beta_B, J_p) trade off along a flat valley
(a little less backscatter, a little brighter J_p), and a joint fit drifts to almost no backscatter
(docs/methods/uw3dgs.md shows it on IUI3-RedSea: a green URI). The dark
pixels break the tie, with the one assumption that the darkest surfaces in view are nearly black.

Why it exists: jointly learning the medium and the Gaussians from the constant beta_prior lets the
Gaussians' colours (initialised from underwater points) absorb the water first, and the photometric loss
is then almost flat along the same valley; the medium stays near where it started. Starting from this
estimate, and from de-hazed point colours, puts the model in the right valley (docs/results.md).
Occlusions and outlier points give wrong observations; the beta_D fit is L1.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass
from typing import TYPE_CHECKING

import torch
from torch import Tensor

from uw3dgs.cameras import Camera

if TYPE_CHECKING:  # annotations only: the estimate needs nothing of the data layer or the fields at run time
    from uw3dgs.data.scene import SceneData
    from uw3dgs.fields.medium import MediumFieldConfig


@dataclass
class MediumFit:
    """A homogeneous medium fitted by `fit_medium`, with what the backscatter fit used."""

    beta_d: Tensor
    """[3] per dataset unit."""
    beta_b: Tensor
    """[3] per dataset unit."""
    b_inf: Tensor
    """[3]"""
    residual: Tensor
    """[3] J': the darkest surfaces' own signal at range 0 (0 where the plain fit was kept)."""
    dark_z: Tensor
    """[K] ranges (dataset units) of the backscatter samples (`dark_pixels`)."""
    dark_color: Tensor
    """[K, 3] their colours."""
    far_quantile: float = 0.0
    """> 0: B_inf was read off the far end of the ranges (this quantile of them), between the two readings below
    (`veiling_light_from_far_end`); 0: given (open water) or fitted with beta_B to the dark samples."""
    veil_below: Tensor | None = None
    """[3] the darkest surfaces' plateau: B_inf fitted with beta_B to the dark samples (a reading from below)."""
    veil_above: Tensor | None = None
    """[3] the median colour of the observations at the far end of the ranges (a reading from above)."""

    @property
    def medium(self) -> tuple[Tensor, Tensor, Tensor]:
        return self.beta_d, self.beta_b, self.b_inf


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
    fit: MediumFit | None = None
    """The fit's details (None when the medium was given as `known`)."""
    observations: tuple[Tensor, Tensor, Tensor] | None = None
    """(point [M], colour [M, 3], range [M] in dataset units) of the fitted points: what the fit saw."""
    positions: Tensor | None = None
    """[P', 3] the fitted points' positions (world units; `observations`' point ids index them): where they are,
    for the identifiability report's check of a medium that varies in space."""
    open_water: OpenWater | None = None
    """What the views said about open water (`estimate_from_views`; None when it was not looked for)."""


def _project(points: Tensor, cam: Camera) -> tuple[Tensor, Tensor, Tensor]:
    """Indices of the `points` [P, 3] that land in `cam`'s image in front of it, and their pixel rows, columns."""
    uv, inside = cam.project(points)
    ids = torch.nonzero(inside).squeeze(1)
    col, row = uv[ids].floor().long().unbind(-1)
    return ids, row, col


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


@dataclass
class OpenWater:
    """What the image cells no initial point lands in say about open water (`find_open_water`)."""

    color: Tensor | None
    """[3] B_inf read off them (the per-channel median of their pixels), None when they are not evidenced as water."""
    empty_cells: int
    """Cells (over all views) that no point lands in."""
    empty_share: float
    """Share of all training pixels in those cells."""
    uniform_share: float
    """Share of the empty cells whose pixels are one colour (standard deviation <= max_std in every channel)."""
    reason: str
    """Why the empty cells were not taken as open water (empty when they were)."""


def find_open_water(points: Tensor, cameras: list[Camera], images: list[Tensor], cells: int, min_share: float,
                    max_std: float = math.inf, min_uniform: float = 0.0) -> OpenWater:
    """B_inf read off open water, where the views give evidence of it: the image regions no initial point lands in.

    Each view is cut into square cells, `cells` across its width. A cell that none of the `points` [P, 3]
    projects into holds nothing SfM could match in any view: open water, whose colour is the veiling light
    B_inf alone (the median shrugs off the odd textureless patch of seabed), or a hole in the points over
    seabed. It is the only direct view of B_inf: from surface points alone B_inf and beta_B trade off along a
    flat valley (above). The cells are taken as water when they hold at least `min_share` of all pixels and at
    least `min_uniform` of them are one colour (pixel standard deviation at most `max_std` in every channel,
    colours in [0, 1]): water is uniform, seabed has texture. Without it a scene with no water in view reads
    B_inf off seabed holes (docs/medium-recovery.md). The defaults check nothing (every empty cell is water).
    """
    water, total, stds = [], 0, []
    for cam, image in zip(cameras, images, strict=True):
        _, row, col = _project(points, cam)
        size = max(1, cam.width // cells)
        grid_h, grid_w = -(-cam.height // size), -(-cam.width // size)
        cell = ((torch.arange(cam.height) // size)[:, None] * grid_w + torch.arange(cam.width) // size).view(-1)
        hit = torch.zeros(grid_h * grid_w, dtype=torch.bool)
        hit[(row // size) * grid_w + col // size] = True
        empty = ~hit[cell]
        pixels = image.reshape(-1, 3)
        water.append(pixels[empty])
        total += cam.width * cam.height
        stds.append(_cell_std(pixels[empty].double(), cell[empty]))
    pixels, stds = torch.cat(water), torch.cat(stds)
    uniform = float((stds <= max_std).double().mean()) if len(stds) else 0.0
    share = len(pixels) / max(total, 1)
    found = OpenWater(None, len(stds), share, uniform, "")
    if share < min_share:
        found.reason = f"the cells no point lands in hold {share:.1%} of the pixels (< {min_share:.1%})"
    elif uniform < min_uniform:
        found.reason = (f"only {uniform:.0%} of the {len(stds)} cells no point lands in are one colour (< "
                        f"{min_uniform:.0%} with pixel std <= {max_std:.3f}): holes in the points over textured "
                        "surfaces, not water")
    else:
        found.color = pixels.float().median(dim=0).values
    return found


def _cell_std(pixels: Tensor, cell: Tensor) -> Tensor:
    """Per cell, the largest over channels of the standard deviation of its pixels [N, 3] (cell ids [N]): [C] for
    the C distinct cells."""
    _, local = torch.unique(cell, return_inverse=True)
    count = torch.bincount(local).double()[:, None]
    mean = torch.zeros(len(count), 3, dtype=torch.float64).index_add_(0, local, pixels) / count
    var = torch.zeros(len(count), 3, dtype=torch.float64).index_add_(0, local, (pixels - mean[local]).square())
    return (var / (count - 1).clamp_min(1)).sqrt().max(dim=1).values


def open_water_color(points: Tensor, cameras: list[Camera], images: list[Tensor], cells: int,
                     min_share: float, max_std: float = math.inf, min_uniform: float = 0.0) -> Tensor | None:
    """B_inf read off open water (`find_open_water`'s colour): None when the empty cells hold less than `min_share`
    of all pixels, or fewer than `min_uniform` of them are one colour (no open water in view)."""
    return find_open_water(points, cameras, images, cells, min_share, max_std, min_uniform).color


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
                    dataset_scale: float, b_inf: Tensor | None = None, min_views: int = 3, dark_bins: int = 10,
                    dark_share: float = 0.01, sfm_cameras: list[Camera] | None = None,
                    known: tuple[Tensor, Tensor, Tensor] | None = None, residual: bool = False,
                    far_quantile: float = 0.0) -> MediumEstimate:
    """Fit a homogeneous medium and per-point clean colours to the points' observations (see module doc).

    Ranges are converted to dataset units (x `dataset_scale`), so the betas are per dataset unit. Only points
    seen by `min_views` or more views constrain the medium; every point's colour is then de-hazed with it:
    from its own observations (least squares), or, for a point no training view sees (SfM also matches test
    views), its input colour at the range it was seen from (`color_ranges` over `sfm_cameras`, the cameras of
    all the views SfM matched; the training `cameras` when None). A colour left underwater would carry the
    water twice once the model adds it. `b_inf` [3], when given (read off open water by `open_water_color`),
    is kept; `dark_bins` and `dark_share` choose the backscatter samples (`dark_pixels`). `known` = (beta_D,
    beta_B, B_inf) skips the fit: the colours are de-hazed with that medium (the true one of a synthetic scene).
    `residual` allows Sea-thru's residual term for dark surfaces that are not black (`fit_medium`). Without
    `b_inf`, `far_quantile` > 0 reads B_inf off the far end of the ranges (`veiling_light_from_far_end`); 0 fits
    it with beta_B to the dark samples.
    """
    points = points.float()
    idx, obs, ranges = observe_points(points, cameras, images)
    keep = torch.bincount(idx, minlength=len(points))[idx] >= min_views
    if not bool(keep.any()):
        raise ValueError(f"no initial point is seen by {min_views} or more training views, so the medium cannot be "
                         "estimated from them: use --model.medium.init prior")
    fitted, local = torch.unique(idx[keep], return_inverse=True)
    observations = (local, obs[keep].float(), ranges[keep] * dataset_scale)
    fit = None if known is not None else fit_medium(*observations, b_inf, dark_bins, dark_share, residual=residual,
                                                    far_quantile=far_quantile)
    medium = tuple(x.float() for x in known) if fit is None else fit.medium
    colors = dehazed_colors(points, point_colors, cameras, dataset_scale, medium, (idx, obs, ranges), sfm_cameras)
    return MediumEstimate(*medium, colors, len(fitted), fit, observations, points[fitted])


def dehazed_colors(points: Tensor, point_colors: Tensor, cameras: list[Camera], dataset_scale: float,
                   medium: tuple[Tensor, Tensor, Tensor], observed: tuple[Tensor, Tensor, Tensor],
                   sfm_cameras: list[Camera] | None = None, factor: Tensor | None = None) -> Tensor:
    """[P, 3] the clean colours of `points` [P, 3] through the homogeneous `medium` (beta_D, beta_B, B_inf [3], per
    dataset unit): from their `observed` = `observe_points(points, cameras, images)`, or, for a point no view sees,
    its SfM colour `point_colors` [P, 3] at the range it was seen from (`color_ranges` over `sfm_cameras`, the
    training `cameras` when None); see `estimate_medium`. `factor` [P] scales the betas per point for a medium that
    varies in space (taken as the mean along each of its rays: a start, which training refines)."""
    idx, obs, ranges = observed
    scale = torch.ones(len(points)) if factor is None else factor.float()
    seen_at = color_ranges(points, cameras if sfm_cameras is None else sfm_cameras) * dataset_scale * scale
    colors = clean_colors(torch.arange(len(points)), point_colors.detach().float(), seen_at, *medium)
    observed_ids, local = torch.unique(idx, return_inverse=True)
    colors[observed_ids] = clean_colors(local, obs.float(), ranges * dataset_scale * scale[idx], *medium)
    return colors


def estimate_from_views(config: MediumFieldConfig, scene: SceneData, train_indices: list[int],
                        known: tuple[Tensor, Tensor, Tensor] | None = None,
                        residual: bool | None = None) -> tuple[MediumEstimate, Tensor | None]:
    """The estimate `--model.medium.init estimate` starts a run from, with the medium `config`'s knobs and the
    training views `train_indices` of `scene`: B_inf read off open water where the views give evidence of it
    (`find_open_water`; unless `known` gives the medium), else off the far, veiled end of the ranges
    (`veiling_light_from_far_end`; the identifiability report says how well it pins it). `residual` overrides
    `config.estimate_residual`. Returns the estimate (what was found of open water in `estimate.open_water`) and the
    open-water colour [3] it used (None: B_inf fitted or known)."""
    cameras, images = [scene.cameras[i] for i in train_indices], [scene.images[i] for i in train_indices]
    found = None
    if known is None and config.open_water_cells > 0:
        found = find_open_water(scene.points.float(), cameras, images, config.open_water_cells,
                                config.open_water_min_share, config.open_water_max_std,
                                config.open_water_min_uniform)
    water = None if found is None else found.color
    estimate = estimate_medium(scene.points, scene.point_colors, cameras, images, float(scene.dataset_scale),
                               b_inf=water, dark_bins=config.dark_bins, dark_share=config.dark_share,
                               sfm_cameras=scene.cameras if config.dehaze_unseen_with_all_poses else None,
                               known=known, residual=config.estimate_residual if residual is None else residual,
                               far_quantile=config.far_end_quantile)
    estimate.open_water = found
    return estimate, water


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


def _refined_argmin(loss: Callable[[Tensor], Tensor], grid: Tensor, rounds: int = 2) -> Tensor:
    """The candidate of the increasing 1-D `grid` with the smallest `loss` (vectorised over candidates),
    refined `rounds` times on an equally fine grid between the best candidate's neighbours."""
    for _ in range(rounds):
        best = int(loss(grid).argmin())
        grid = torch.linspace(float(grid[max(best - 1, 0)]), float(grid[min(best + 1, len(grid) - 1)]), len(grid),
                              dtype=grid.dtype)
    return grid[int(loss(grid).argmin())]


def _beta_grid(z: Tensor, steps: int) -> Tensor:
    """Candidate betas: optical depths 0.01 to 10 at the median range, log-spaced, whatever the units."""
    return torch.logspace(math.log10(0.01), math.log10(10.0), steps, dtype=torch.float64) / float(z.median())


def dark_pixels(z: Tensor, color: Tensor, bins: int = 10, share: float = 0.01) -> tuple[Tensor, Tensor]:
    """The darkest `share` (by RGB sum, at least one) of the observations color [M, 3] in each of `bins`
    equally populated range bins of z [M]: Sea-thru's backscatter samples. Returns their z [K], colours [K, 3]."""
    edges = torch.quantile(z.double(), torch.linspace(0, 1, bins + 1, dtype=torch.float64))
    which = torch.bucketize(z.double(), edges[1:-1])
    picked = []
    for b in range(bins):
        members = torch.nonzero(which == b).squeeze(1)
        if len(members):
            order = color[members].sum(dim=-1).argsort()
            picked.append(members[order[:max(1, int(share * len(members)))]])
    picked = torch.cat(picked)
    return z[picked], color[picked]


def fit_backscatter(z: Tensor, color: Tensor, b_inf: Tensor | None = None, steps: int = 300,
                    max_samples: int = 1024) -> tuple[Tensor, Tensor]:
    """Least-squares fit of B_inf (1 - exp(-beta_B z)) to backscatter samples color [K, 3] at ranges z [K]
    (`dark_pixels`; a random `max_samples` of them), per channel. `b_inf` [3] fixes the veiling light;
    without it B_inf is searched too. Returns beta_B, B_inf [3]."""
    if len(z) > max_samples:  # the B_inf search costs candidates^2 x samples
        keep = torch.randperm(len(z), generator=torch.Generator().manual_seed(0))[:max_samples]
        z, color = z[keep], color[keep]
    z, color = z.double(), color.double()
    betas = _beta_grid(z, steps)
    beta_b, veil = [], []
    for c in range(3):
        def sse(beta: Tensor, v: Tensor, y: Tensor = color[:, c]) -> Tensor:  # candidates broadcast over samples
            return (v[..., None] * (1 - torch.exp(-beta[..., None] * z)) - y).square().mean(-1)

        if b_inf is None:  # profile beta_B out on its grid, then search B_inf
            v = _refined_argmin(lambda v: torch.cat([sse(betas[None, :], chunk[:, None]).min(-1).values
                                                     for chunk in v.split(8)]),
                                torch.linspace(0.01, 0.99, 99, dtype=torch.float64))
        else:
            v = b_inf[c].double()
        beta_b.append(_refined_argmin(lambda beta, v=v: sse(beta, v.expand_as(beta)), betas))
        veil.append(v)
    return torch.stack(beta_b).float(), torch.stack(veil).float()


def fit_attenuation(point: Tensor, color: Tensor, z: Tensor, beta_b: Tensor, b_inf: Tensor, steps: int = 300,
                    max_observations: int = 50_000) -> Tensor:
    """L1 fit of beta_D [3] to observations color [M, 3] of points point [M] (0..P-1, every value present) at
    ranges z [M], with the backscatter known; each J_p in closed form per candidate. A random
    `max_observations` of them enter (so big SfM models cost no more than small ones)."""
    subset = torch.randperm(len(point), generator=torch.Generator().manual_seed(0))[:max_observations]
    points, local = torch.unique(point[subset], return_inverse=True)
    z, color = z[subset].float(), color[subset].float()
    betas = _beta_grid(z, steps).float()
    beta_d = []
    for c in range(3):
        def loss(candidates: Tensor, c: int = c) -> Tensor:
            return torch.cat([
                _profiled_residual(local, color[:, c], z, chunk, beta_b[c].expand_as(chunk),
                                   b_inf[c].expand_as(chunk), len(points))[0].abs().mean(-1)
                for chunk in candidates.split(32)])

        beta_d.append(_refined_argmin(loss, betas))
    return torch.stack(beta_d)


def backscatter_curve(z: Tensor, beta_b: Tensor, b_inf: Tensor, beta_d: Tensor | None = None,
                      residual: Tensor | None = None) -> Tensor:
    """Colours [K, 3] of the darkest surfaces at ranges z [K]: B_inf (1 - exp(-beta_B z)) + J' exp(-beta_D z)
    (the residual term only when `beta_d` and `residual` [3] are given)."""
    z = z[:, None]
    curve = b_inf * (1 - torch.exp(-beta_b * z))
    return curve if residual is None else curve + residual * torch.exp(-beta_d * z)


def fit_backscatter_residual(z: Tensor, color: Tensor, beta_d: Tensor, b_inf: Tensor | None = None,
                             steps: int = 300) -> tuple[Tensor, Tensor, Tensor]:
    """Least-squares fit of B_inf (1 - exp(-beta_B z)) + J' exp(-beta_D z) to backscatter samples color [K, 3] at
    ranges z [K], per channel, with beta_D [3] given: for each candidate beta_B the model is linear in (B_inf, J'),
    solved in closed form (J' >= 0, B_inf in [0.001, 1]). `b_inf` [3] fixes the veiling light. Returns beta_B,
    B_inf, J' [3]."""
    z, color = z.double(), color.double()
    betas = _beta_grid(z, steps)
    beta_b, veil, residual = [], [], []
    for c in range(3):
        y, d = color[:, c], torch.exp(-beta_d[c].double() * z)

        def solve(beta: Tensor, y: Tensor = y, d: Tensor = d, c: int = c) -> tuple[Tensor, Tensor, Tensor]:
            """(B_inf, J', mean squared error) [G] for candidates beta [G]."""
            a = 1 - torch.exp(-beta[:, None] * z)
            saa, sad, say = (a * a).sum(-1), (a * d).sum(-1), (a * y).sum(-1)
            sdd, sdy = (d * d).sum(), (d * y).sum()
            if b_inf is None:
                det = (saa * sdd - sad * sad).clamp_min(1e-300)
                v = (say * sdd - sad * sdy) / det
                v = torch.where((saa * sdy - sad * say) / det < 0, say / saa, v).clamp(1e-3, 1.0)
            else:
                v = b_inf[c].double().expand_as(beta)
            r = ((sdy - v * sad) / sdd).clamp_min(0.0)
            return v, r, (v[:, None] * a + r[:, None] * d - y).square().mean(-1)

        best = _refined_argmin(lambda beta: solve(beta)[2], betas)
        v, r, _ = solve(best[None])
        beta_b.append(best)
        veil.append(v[0])
        residual.append(r[0])
    return torch.stack(beta_b).float(), torch.stack(veil).float(), torch.stack(residual).float()


def _bic(mse: Tensor, samples: int, parameters: int) -> Tensor:
    """Bayesian information criterion of a least-squares fit with Gaussian errors (lower is better)."""
    return samples * torch.log(mse.clamp_min(1e-12)) + parameters * math.log(samples)


def far_end_color(z: Tensor, color: Tensor, quantile: float) -> tuple[float, Tensor]:
    """The far end of observations color [M, 3] at ranges z [M]: (z_far, the `quantile` of the ranges; the median
    colour [3] of the observations at z_far or beyond)."""
    z_far = float(torch.quantile(z.double(), quantile))
    return z_far, color[z >= z_far].float().median(dim=0).values


def veiling_light_from_far_end(point: Tensor, color: Tensor, z: Tensor, quantile: float, bins: int = 10,
                               share: float = 0.01, residual: bool = False, steps: int = 300,
                               max_observations: int = 50_000) -> tuple[Tensor, Tensor, Tensor]:
    """B_inf [3] without open water, off the far, veiled end of the ranges, where every colour converges to it.
    Two readings bracket it there: the darkest surfaces' plateau (B_inf fitted with beta_B to the dark samples,
    `fit_medium`; they approach the veiling light from below, and occluded or misread samples pull the plateau
    lower still) and the median colour of the observations beyond the `quantile` of the ranges (the typical surface,
    brighter than the water, approaches it from above). B_inf is the middle of the two; half their distance bounds
    its error where the bracket holds (the identifiability report checks it, and that the far end is veiled;
    docs/medium-report.md, "B_inf without open water"). Returns (B_inf, below, above)."""
    below = fit_medium(point, color, z, None, bins, share, residual=residual, steps=steps,
                       max_observations=max_observations).b_inf
    above = far_end_color(z, color, quantile)[1]
    return (below + above) / 2, below, above


def fit_medium(point: Tensor, color: Tensor, z: Tensor, b_inf: Tensor | None = None, bins: int = 10,
               share: float = 0.01, residual: bool = False, rounds: int = 3, steps: int = 300,
               max_observations: int = 50_000, far_quantile: float = 0.0) -> MediumFit:
    """The homogeneous medium of observations color [M, 3] of points point [M] (0..P-1, every value present)
    at ranges z [M] > 0: beta_B (and B_inf unless `b_inf` [3] is given) from the dark pixels, then beta_D; with
    `residual`, up to `rounds` rounds of the residual backscatter fit (with the last beta_D) and beta_D again, the
    residual kept per channel where it lowers the BIC of the dark samples. Without `b_inf` and with `far_quantile`
    > 0, B_inf is read off the far end of the ranges first (`veiling_light_from_far_end`), then held. `steps`
    candidates per 1-D search; `max_observations` enter the beta_D fit. `clean_colors` gives the J_p."""
    if b_inf is None and far_quantile > 0:
        veil, below, above = veiling_light_from_far_end(point, color, z, far_quantile, bins, share, residual, steps,
                                                        max_observations)
        fit = fit_medium(point, color, z, veil, bins, share, residual, rounds, steps, max_observations)
        fit.far_quantile, fit.veil_below, fit.veil_above = far_quantile, below, above
        return fit
    dark_z, dark_color = dark_pixels(z, color, bins, share)
    beta_b, veil = fit_backscatter(dark_z, dark_color, b_inf=b_inf, steps=steps)
    beta_d = fit_attenuation(point, color, z, beta_b, veil, steps, max_observations)
    j_prime = torch.zeros(3)
    if residual:
        plain_b, plain_veil = beta_b, veil
        plain = (backscatter_curve(dark_z, beta_b, veil) - dark_color).square().mean(0)
        free = 1 if b_inf is None else 0
        for _ in range(rounds):
            rb, rv, rj = fit_backscatter_residual(dark_z, dark_color, beta_d, b_inf, steps)
            mse = (backscatter_curve(dark_z, rb, rv, beta_d, rj) - dark_color).square().mean(0)
            use = _bic(mse, len(dark_z), 2 + free) < _bic(plain, len(dark_z), 1 + free)
            if not bool(use.any()) and not bool(j_prime.any()):
                break
            beta_b, veil = torch.where(use, rb, plain_b), torch.where(use, rv, plain_veil)
            j_prime = torch.where(use, rj, torch.zeros(3))
            beta_d = fit_attenuation(point, color, z, beta_b, veil, steps, max_observations)
    return MediumFit(beta_d, beta_b, veil, j_prime, dark_z, dark_color)
