"""Does this scene constrain its medium? A per-parameter report on the point-based estimate, before training.

The estimate (fields/medium_estimate.py) always returns nine numbers; whether the data pinned them is another
matter. A scene seen over a short span of ranges, with no open water and no near-black surfaces, fits the
images equally well with a wide range of backscatter curves, and the fit returns one of them with nothing to
say it is a guess. Two checks, each relative to the estimate, and a parameter is identifiable when both stay
within +-`tolerance`:

- the bootstrap: every fitted point is resampled with replacement (`resamples` times) and the medium fitted
  again; half the width of the 5-95% interval (how much the numbers depend on which points SfM found);
- the assumption: the medium fitted again with the other backscatter model (with Sea-thru's residual term if
  the estimate had none, without it if it had), i.e. how much the numbers depend on whether the darkest
  surfaces are black, which no fit can check (a bias, which the bootstrap does not see).

A weak parameter is reported with the scene's properties that explain it:

- the span of ranges in optical depths (beta (z90 - z10)): under about 1, a backscatter curve is nearly a
  straight line and its bend (which separates B_inf from beta_B) is not seen;
- open water: the only direct view of B_inf;
- the backscatter samples (the darkest observations per range bin): how many, and how far above the fitted
  backscatter curve they lie, as a share of B_inf (not black: the residual term, or a beta_B biased high).

B_inf read off open water is a measurement, not a fit: it is reported as identifiable, but only where the views
gave evidence of open water (`find_open_water`: most empty cells one colour). Otherwise B_inf was read off the far
end of the ranges (`veiling_light_from_far_end`) or fitted, and two more checks say whether the far end pins it
(`far_end`; every refit of the report reads B_inf the way the estimate did):

- veiled: the surfaces' own signal at the far end (the `far_quantile` of the ranges), exp(-beta_D z_far), at most
  `max_far_transmission`: there every colour has converged to B_inf; short of it B_inf is an extrapolation;
- agreement: half the distance between the far end's two readings (the darkest surfaces' plateau, from below; the
  median colour of the observations beyond z_far, from above), which bounds the error of their middle where they
  bracket B_inf, at most `far_end_tolerance` of it (a B_inf fitted to the dark samples alone: its distance to
  that median colour).

The betas of a channel whose B_inf is not identifiable are not either: they are fitted with it held.

Three limits no refit shows (docs/medium-report.md, "The last three misses, and 9C"):

- resolution: the images round every colour to a grey level (`grey_level`), so a B_inf of a few grey levels is
  not known to the tolerance (it does not flag the betas: its error is under what their fits resolve);
- drift: over a span of tau optical depths a change of the surfaces' colours with range that is not the water's
  (`color_drift`) moves beta_D by about color_drift / tau;
- dark surfaces that are not black: `dark_floor` refits beta_B to the dark samples less the own light of a
  `dark_albedo` surface, which no fit can tell from black.

And one statement about the scene rather than the medium: `recoverable_range`, the range beyond which a typical
seabed colour sends under one grey level through the water, and the share of points no view sees nearer: their
water-free colour cannot be recovered, however right the medium.

A medium that varies in space (a plume, a turbid layer) is fitted by a homogeneous model as an average, as
stable under the bootstrap as a homogeneous one. `spatial_check` fits the two halves of the scene along each of
its two main horizontal axes (the principal axes of the fitted points) on their own, B_inf held at the estimate,
over the same window of ranges: where beta_D of the halves disagrees by more than `spatial_tolerance` and more
than `spatial_noise_factor` times the bootstrap spread in `spatial_min_channels` of the channels the other checks
pass, the betas vary in space and are flagged (all six: particles that scatter also attenuate).
It sees only variation across the seabed: a turbid layer that every ray crosses the same way (cameras at one
altitude) gives every pixel the same ray-mean beta, which a homogeneous medium matches, and is not seen.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import asdict, dataclass

import torch
from torch import Tensor

from uw3dgs.fields.medium_estimate import (
    MediumFit,
    OpenWater,
    clean_colors,
    far_end_color,
    fit_backscatter,
    fit_medium,
)
from uw3dgs.options import CheckedConfig, check_number

CHANNELS = "RGB"


@dataclass(frozen=True)
class IdentifiabilityConfig(CheckedConfig):
    """The report's thresholds (`assess_medium`)."""

    tolerance: float = 0.15
    """A parameter is identifiable when the bootstrap half-spread and the other backscatter model's change stay
    within this share of its value (the medium-recovery benchmark's bar for the learned medium)."""
    resamples: int = 8
    """Bootstrap fits (points resampled with replacement)."""
    seed: int = 0
    """Seed of the bootstrap's resampling."""
    steps: int = 100
    """Candidates per 1-D search in the report's fits (the estimate itself uses 300)."""
    max_observations: int = 20_000
    """Observations per beta_D fit in the report's fits."""
    far_quantile: float = 0.9
    """The far end of the ranges: this quantile of the observations' ranges, z_far (B_inf fitted without open
    water; an estimate read off the far end brings its own, `MediumFit.far_quantile`)."""
    max_far_transmission: float = 0.2
    """A fitted B_inf is pinned by the far end only where exp(-beta_D z_far), the share of the surfaces' own signal
    still there, is at most this: beyond it every colour is within that share of the way to B_inf."""
    far_end_tolerance: float = 0.15
    """B_inf read off the far end: half the distance between its two readings (the darkest surfaces' plateau and the
    far observations' median colour), which bounds its error where they bracket it, at most this share of it.
    B_inf fitted to the dark samples alone: its distance to the far observations' median colour."""
    spatial_tolerance: float = 0.3
    """The betas vary in space when beta_D fitted to two halves of the scene differs by more than this share of
    the estimate (docs/medium-recovery.md, "What the report sees of a varying medium")..."""
    spatial_noise_factor: float = 2.0
    """... and by more than this many times the bootstrap half-spread (a half has half the points: its fits
    scatter more)."""
    spatial_min_channels: int = 2
    """... in at least this many of the three channels, counting only channels whose beta_D passes the other two
    checks: particles that vary in space scale every channel's beta alike, while a channel the data hardly pins
    (blue beta_D on the clear Jerlov types, every channel over a narrow span of ranges) scatters alone."""
    spatial_min_points: int = 50
    """Least fitted points in each half for the spatial check (fewer: not run)."""
    grey_level: float = 1 / 255
    """One grey level of the images (8-bit): a colour is read to within half of it, so a B_inf under
    0.5 grey_level / tolerance (3.3 grey levels at 8 bits and 15%) cannot be measured to the tolerance."""
    color_drift: float = 0.06
    """A relative change of the surfaces' colours over the span of ranges that is not the water's (the texture
    blurs with distance, the relief hides and shows shading): beta_D read over a span of tau optical depths moves
    by about color_drift / tau, so it is flagged where that exceeds the tolerance (under 0.4 optical depths at 6%
    and 15%). Calibrated on the synthetic scene's homogeneous variants (docs/medium-report.md, "The last three
    misses, and 9C")."""
    dark_albedo: float = 0.03
    """The albedo the darkest surfaces in view may have: a few % for dark rock, sponges and shadowed crevices.
    Their own light, dark_albedo exp(-beta_D z), is what the backscatter fit would read as backscatter if they
    are not black: beta_B is flagged where subtracting it from the dark samples moves beta_B by more than the
    tolerance (the synthetic scene's dark patches are 3%; on the benchmark's rows 2% gives the same verdicts, 5%
    also flags `no-open-water`'s green beta_B, 13% off)."""

    def check_options(self) -> None:
        super().check_options()
        for name in ("tolerance", "max_far_transmission", "far_end_tolerance", "spatial_tolerance",
                     "spatial_noise_factor", "color_drift", "dark_albedo"):
            check_number(self, name, ge=0)
        check_number(self, "spatial_min_channels", ge=1, le=3, integer=True)
        for name in ("resamples", "steps", "max_observations", "spatial_min_points"):
            check_number(self, name, ge=1, integer=True)
        check_number(self, "far_quantile", gt=0, lt=1)
        check_number(self, "grey_level", gt=0, lt=1)


@dataclass
class ParameterCheck:
    name: str
    """'beta_D', 'beta_B' or 'B_inf'."""
    channel: str
    """'R', 'G' or 'B'."""
    value: float
    """The estimate (betas per dataset unit)."""
    spread: float
    """Half the width of the bootstrap 5-95% interval, relative to the value (0 for B_inf read off open water)."""
    assumption: float
    """|value with the other backscatter model - value|, relative to the value."""
    identifiable: bool
    reason: str
    """Why not (empty when identifiable)."""


@dataclass
class IdentifiabilityReport:
    range_span: tuple[float, float]
    """(z10, z90): the 10th and 90th percentile of the observations' ranges, dataset units."""
    optical_depth_span: dict[str, list[float]]
    """'beta_D', 'beta_B' -> [3]: beta (z90 - z10), per channel."""
    open_water: bool
    """B_inf was read off open water."""
    open_water_reason: str
    """Why empty image cells were not taken as open water (empty when B_inf was read off it, or not looked for)."""
    far_range: float
    """z_far: the `far_quantile` of the observations' ranges, dataset units."""
    far_transmission: list[float]
    """[3] exp(-beta_D z_far): the share of the surfaces' own signal left at the far end."""
    far_color: list[float]
    """[3] the median colour of the observations beyond z_far (-> B_inf where the far end is veiled)."""
    spatial_disagreement: dict[str, list[float]] | None
    """'beta_D', 'beta_B' -> [3]: the largest difference between the fits of two halves of the scene, relative to
    the estimate (None: not checked, no positions or too few points)."""
    varies_in_space: bool
    """The halves disagree (`spatial_check`): the betas are flagged as varying in space."""
    dark_samples: int
    """Backscatter samples the fit used."""
    dark_excess: list[float]
    """[3] the darkest surfaces' own signal at the median range, J' exp(-beta_D z50) / B_inf, from the residual fit
    (this one or the other): ~0 for black surfaces."""
    residual: list[float]
    """[3] the fitted residual term J' (0 where not used)."""
    dark_floor_shift: list[float]
    """[3] |beta_B fitted to the dark samples less their own light if they reflect `dark_albedo` - beta_B| / beta_B,
    both with B_inf held at the estimate (`dark_floor`)."""
    dark_floor_share: list[float]
    """[3] that own light at the near end of the dark samples' ranges (their 10th percentile), where the backscatter's
    rise sets beta_B, as a share of the fitted backscatter there."""
    recoverable_range: list[float]
    """[3] the range (dataset units) beyond which a typical seabed colour (the median de-hazed colour of the fitted
    points) sends less than one grey level through the water, exp(-beta_D z): the water-free image cannot be
    recovered from a view farther than that (`recoverable_range`)."""
    unrecoverable_share: list[float]
    """[3] the share of the fitted points that no view sees nearer than the recoverable range."""
    tolerance: float
    resamples: int
    checks: list[ParameterCheck]
    spatial_undecided: bool = False
    """The halves are farther apart than the spatial tolerance, but the estimate's own spread or its assumptions move
    it as much: whether the medium varies cannot be told (not 'homogeneous')."""

    def weak(self, name: str) -> list[bool]:
        """[3] whether `name`'s channels are not identifiable."""
        return [not c.identifiable for c in self.checks if c.name == name]

    def to_json(self) -> dict:
        return asdict(self)

    def lines(self) -> list[str]:
        """Human-readable lines for the log: one per parameter, then the scene's properties."""
        out = []
        for name in ("beta_D", "beta_B", "B_inf"):
            checks = [c for c in self.checks if c.name == name]
            values = ", ".join(f"{c.value:.3f} +-{max(c.spread, c.assumption):.0%}" for c in checks)
            verdict = "identifiable" if all(c.identifiable for c in checks) else "; ".join(
                f"{c.channel} not identifiable: {c.reason}" for c in checks if not c.identifiable)
            out.append(f"{name} ({values}): {verdict}")
        z10, z90 = self.range_span
        water = "in view" if self.open_water else "not in view" + (f": {self.open_water_reason}"
                                                                   if self.open_water_reason else "")
        out.append(f"ranges {z10:.2f}-{z90:.2f} (10-90%), {self.dark_samples} backscatter samples, open water {water}")
        reach = "/".join(f"{z:.1f}" for z in self.recoverable_range)
        beyond = "/".join(f"{x:.0%}" for x in self.unrecoverable_share)
        out.append(f"the water-free image is recoverable to range {reach} (R/G/B; beyond it a typical surface colour "
                   f"sends under one grey level through the water): {beyond} of the fitted points are seen only "
                   "beyond it")
        if self.spatial_disagreement is not None:
            halves = "; ".join(f"{name} {'/'.join(f'{x:.0%}' for x in v)}"
                               for name, v in self.spatial_disagreement.items())
            verdict = "varies in space" if self.varies_in_space else (
                "cannot tell whether the medium varies: the estimate's own spread or assumptions (above) move it as "
                "much" if self.spatial_undecided else "homogeneous within the tolerance")
            out.append(f"halves of the scene disagree by {halves}: {verdict}")
        return out


def bootstrap_observations(point: Tensor, generator: torch.Generator) -> tuple[Tensor, Tensor]:
    """Resample the points [M] (ids 0..P-1) with replacement, each with all its observations. Returns (new point
    ids [M'], the observations' indices into the originals [M']); a point drawn twice becomes two points."""
    num_points = int(point.max()) + 1
    order = torch.argsort(point, stable=True)
    counts = torch.bincount(point, minlength=num_points)
    starts = torch.cumsum(counts, 0) - counts
    pick = torch.randint(num_points, (num_points,), generator=generator)
    n = counts[pick]
    new_ids = torch.arange(num_points).repeat_interleave(n)
    first = torch.cumsum(n, 0) - n
    offsets = starts[pick].repeat_interleave(n) + torch.arange(int(n.sum())) - first.repeat_interleave(n)
    return new_ids, order[offsets]


def _reason(name: str, c: int, report: IdentifiabilityReport) -> str:
    """The scene's properties that explain a weak parameter `name`, channel `c`."""
    hints = []
    depth = report.optical_depth_span["beta_B" if name != "beta_D" else "beta_D"][c]
    if depth < 1.0:
        hints.append(f"the ranges span only {depth:.2f} optical depths")
    if name != "beta_D" and not report.open_water:
        hints.append("no open water in view")
    if name != "beta_D" and report.dark_excess[c] > 0.1:
        hints.append(f"the darkest surfaces may not be black (their own signal {report.dark_excess[c]:.0%} of B_inf "
                     "at the median range)")
    if name != "beta_D" and report.dark_samples < 30:
        hints.append(f"only {report.dark_samples} backscatter samples")
    return ", ".join(hints) or "the bootstrap fits disagree"


def far_end(z: Tensor, color: Tensor, beta_d: Tensor, quantile: float) -> tuple[float, Tensor, Tensor]:
    """The far, veiled end of the ranges z [M] (dataset units) of observations color [M, 3]: (z_far, the `quantile`
    of the ranges; exp(-beta_D z_far) [3], the share of the surfaces' own signal left there; the median colour [3]
    of the observations beyond z_far, which tends to B_inf as that share goes to 0)."""
    z_far, far_color = far_end_color(z, color, quantile)
    return z_far, torch.exp(-beta_d.double() * z_far).float(), far_color


def dark_floor(fit: MediumFit, albedo: float, steps: int) -> tuple[Tensor, Tensor]:
    """What if the darkest surfaces are not black but reflect `albedo`? Their own light, albedo exp(-beta_D z),
    would be read as backscatter. Returns ([3] |beta_B fitted to the dark samples less that light - beta_B fitted
    to them as they are| / the latter, both with B_inf held at `fit`'s; [3] that light at the near end of the dark
    samples' ranges (their 10th percentile), where the backscatter's rise sets beta_B, as a share of `fit`'s
    backscatter there)."""
    z, dark = fit.dark_z, fit.dark_color
    own = albedo * torch.exp(-fit.beta_d * z[:, None])
    plain = fit_backscatter(z, dark, b_inf=fit.b_inf, steps=steps)[0].double()
    lit = fit_backscatter(z, dark - own, b_inf=fit.b_inf, steps=steps)[0].double()
    near = float(torch.quantile(z.double(), 0.1))
    back = fit.b_inf.double() * (1 - torch.exp(-fit.beta_b.double() * near))
    share = albedo * torch.exp(-fit.beta_d.double() * near) / back.clamp_min(1e-6)
    return (lit - plain).abs() / plain.clamp_min(1e-6), share


def recoverable_range(point: Tensor, color: Tensor, z: Tensor, fit: MediumFit, grey_level: float
                      ) -> tuple[Tensor, Tensor]:
    """How far the water-free image can be recovered: ([3] the range beyond which a typical seabed colour J (the
    median de-hazed colour of the points) sends under one grey level through the water, J exp(-beta_D z) <
    grey_level, so the images hold no trace of it; [3] the share of the points (ids `point` [M] of the observations
    color [M, 3] at ranges z [M]) that no view sees nearer than that: their water-free colour is a guess)."""
    typical = clean_colors(point, color, z, *fit.medium).double().median(dim=0).values
    reach = torch.log((typical / grey_level).clamp_min(1.0)) / fit.beta_d.double().clamp_min(1e-6)
    nearest = torch.full((int(point.max()) + 1,), math.inf, dtype=torch.float64).scatter_reduce(
        0, point, z.double(), "amin")
    return reach, (nearest[:, None] > reach).double().mean(0)


def principal_axes(positions: Tensor) -> Tensor:
    """[2, 3] the two main axes of the points [P, 3] (their largest principal components): across the seabed for a
    survey, whatever the world's orientation."""
    centred = positions.double() - positions.double().mean(0)
    return torch.linalg.svd(centred, full_matrices=False)[2][:2].to(positions.dtype)


def spatial_check(point: Tensor, color: Tensor, z: Tensor, positions: Tensor, b_inf: Tensor, bins: int, share: float,
                  residual: bool, config: IdentifiabilityConfig) -> dict[str, list[float]] | None:
    """Does the medium vary across the scene? The observations (point ids [M] into positions [P, 3], colours [M, 3],
    ranges [M]) are split into the two halves of the points along each `principal_axes`, each half fitted on its
    own with B_inf [3] held; returns 'beta_D', 'beta_B' -> [3] the largest |half 1 - half 2| / value of the whole,
    over both axes (None where a half has fewer than `spatial_min_points` points)."""
    whole = fit_medium(point, color, z, b_inf, bins, share, residual=residual, steps=config.steps,
                       max_observations=config.max_observations)
    disagreement = torch.zeros(2, 3, dtype=torch.float64)
    for axis in principal_axes(positions):
        coord = positions @ axis
        side = coord > coord.median()
        if min(int(side.sum()), int((~side).sum())) < config.spatial_min_points:
            return None
        # the same window of ranges for both halves: with a slightly wrong B_inf the fitted betas depend on the
        # ranges fitted, and halves of a forward-looking survey are its near and its far part
        bounds = [torch.quantile(z[half[point]].double(), torch.tensor([0.1, 0.9], dtype=torch.float64))
                  for half in (side, ~side)]
        lo, hi = max(float(b[0]) for b in bounds), min(float(b[1]) for b in bounds)
        window = (z >= lo) & (z <= hi)
        fits = []
        for half in (side, ~side):
            rows = half[point] & window
            if int(torch.unique(point[rows]).numel()) < config.spatial_min_points:
                return None
            ids = torch.unique(point[rows], return_inverse=True)[1]
            fit = fit_medium(ids, color[rows], z[rows], b_inf, bins, share, residual=residual, steps=config.steps,
                             max_observations=config.max_observations)
            fits.append(torch.stack([fit.beta_d, fit.beta_b]).double())
        scale = torch.stack([whole.beta_d, whole.beta_b]).double().abs().clamp_min(1e-6)
        disagreement = torch.maximum(disagreement, (fits[0] - fits[1]).abs() / scale)
    return {"beta_D": disagreement[0].tolist(), "beta_B": disagreement[1].tolist()}


def assess_medium(point: Tensor, color: Tensor, z: Tensor, fit: MediumFit, b_inf: Tensor | None, bins: int,
                  share: float, residual: bool, config: IdentifiabilityConfig | None = None,
                  positions: Tensor | None = None, open_water: OpenWater | None = None,
                  **options) -> IdentifiabilityReport:
    """The report for `fit` of observations color [M, 3] of points point [M] at ranges z [M] (dataset units), as
    `fit_medium` made it (`b_inf` [3] read off open water, or None; `bins`, `share`, `residual` as given to it).
    `config` holds the thresholds (`options` replace some of its fields, e.g. resamples=4); `positions` [P, 3], the
    points' positions (`MediumEstimate.positions`), allow the check of a medium that varies in space; `open_water`
    (`MediumEstimate.open_water`) says why B_inf was not read off open water."""
    config = dataclasses.replace(config or IdentifiabilityConfig(), **options)
    tolerance = config.tolerance
    generator = torch.Generator().manual_seed(config.seed)
    far_quantile = fit.far_quantile  # B_inf read off the far end: every refit reads it the same way
    other_fit = fit_medium(point, color, z, b_inf, bins, share, residual=not residual, steps=config.steps,
                           max_observations=config.max_observations, far_quantile=far_quantile)
    other, with_residual = other_fit.medium, fit if residual else other_fit
    fits = []
    for _ in range(config.resamples):
        ids, rows = bootstrap_observations(point, generator)
        fits.append(fit_medium(ids, color[rows], z[rows], b_inf, bins, share, residual=residual, steps=config.steps,
                               max_observations=config.max_observations, far_quantile=far_quantile).medium)
    z10, z90 = (float(q) for q in torch.quantile(z.double(), torch.tensor([0.1, 0.9], dtype=torch.float64)))
    z50 = float(z.double().median())
    excess = with_residual.residual * torch.exp(-with_residual.beta_d * z50) / with_residual.b_inf.clamp_min(1e-3)
    z_far, transmission, far_color = far_end(z, color, fit.beta_d, far_quantile or config.far_quantile)
    floor_shift, floor_share = dark_floor(fit, config.dark_albedo, config.steps)
    reach, beyond = recoverable_range(point, color, z, fit, config.grey_level)
    spatial = None if positions is None else spatial_check(point, color, z, positions, fit.b_inf, bins, share,
                                                           residual, config)
    report = IdentifiabilityReport(
        range_span=(z10, z90),
        optical_depth_span={name: (beta * (z90 - z10)).tolist() for name, beta in (("beta_D", fit.beta_d),
                                                                                  ("beta_B", fit.beta_b))},
        open_water=b_inf is not None,
        open_water_reason="" if b_inf is not None or open_water is None else open_water.reason,
        far_range=z_far, far_transmission=transmission.tolist(), far_color=far_color.tolist(),
        spatial_disagreement=spatial, varies_in_space=False, dark_samples=len(fit.dark_z),
        dark_excess=excess.tolist(),
        residual=fit.residual.tolist(), dark_floor_shift=floor_shift.tolist(), dark_floor_share=floor_share.tolist(),
        recoverable_range=reach.tolist(), unrecoverable_share=beyond.tolist(), tolerance=tolerance,
        resamples=config.resamples, checks=[])
    spreads = {}
    for k, name in enumerate(("beta_D", "beta_B", "B_inf")):
        values = torch.stack([f[k] for f in fits]).double()
        lo, hi = torch.quantile(values, torch.tensor([0.05, 0.95], dtype=torch.float64), dim=0)
        estimate = fit.medium[k].double()
        scale = estimate.abs().clamp_min(1e-6)
        spreads[name] = ((hi - lo) / 2 / scale).tolist()
    if spatial is not None:  # only channels whose beta_D the whole scene pins can show that it varies
        shift = ((other_fit.beta_d.double() - fit.beta_d.double()).abs() / fit.beta_d.double().clamp_min(1e-6))
        varying = sum(d > config.spatial_tolerance and d > config.spatial_noise_factor * s and s <= tolerance
                      and float(a) <= tolerance
                      for d, s, a in zip(spatial["beta_D"], spreads["beta_D"], shift, strict=True))
        report.varies_in_space = varying >= config.spatial_min_channels
        apart = sum(d > config.spatial_tolerance for d in spatial["beta_D"]) >= config.spatial_min_channels
        report.spatial_undecided = apart and not report.varies_in_space
    checks, pinned = {}, {}
    for k, name in reversed(list(enumerate(("beta_D", "beta_B", "B_inf")))):  # B_inf first: the betas depend on it
        estimate = fit.medium[k].double()
        scale = estimate.abs().clamp_min(1e-6)
        assumption = ((other[k].double() - estimate).abs() / scale).tolist()
        for c in range(3):
            measured = name == "B_inf" and b_inf is not None
            s, a = (0.0, 0.0) if measured else (spreads[name][c], assumption[c])
            why = [f"bootstrap spread +-{s:.0%}"] if s > tolerance else []
            if a > tolerance:
                why.append(f"{a:.0%} off if the darkest surfaces are {'' if residual else 'not '}black")
            reason = f"{', '.join(why)} (> {tolerance:.0%}): {_reason(name, c, report)}" if why else ""
            more = [] if name != "B_inf" or measured else _far_end_reasons(c, float(estimate[c]), fit, report,
                                                                           config)
            if name == "B_inf":
                pinned[c] = not reason and not more
                # too faint to resolve, but its error (under half a grey level) leaves the betas' verdicts alone
                more += _resolution_reasons(float(estimate[c]), config)
            elif not pinned[c]:
                more.append("fitted with a B_inf that is not pinned (above): the backscatter it leaves for "
                            "beta_B and beta_D moves with it")
            if name == "beta_D":
                more += _drift_reasons(report.optical_depth_span["beta_D"][c], config)
            if name == "beta_B" and floor_shift[c] > tolerance:
                more.append(f"{floor_shift[c]:.0%} off if the darkest surfaces reflect {config.dark_albedo:.0%} "
                            f"(> {tolerance:.0%}): their own light, attenuated with the estimated beta_D, would be "
                            f"read as backscatter ({floor_share[c]:.0%} of it at the near end of their ranges)")
            if name != "B_inf" and report.varies_in_space:
                more.append(f"varies in space: the halves of the scene give values {spatial[name][c]:.0%} apart "
                            f"(beta_D {'/'.join(f'{d:.0%}' for d in spatial['beta_D'])}, > "
                            f"{config.spatial_tolerance:.0%} in {config.spatial_min_channels}+ channels); a "
                            "homogeneous estimate is an average, the VM grid must learn the field")
            reason = "; ".join(r for r in (reason, *more) if r)
            checks[(name, c)] = ParameterCheck(name, CHANNELS[c], float(estimate[c]), s, a, not reason, reason)
    report.checks = [checks[(name, c)] for name in ("beta_D", "beta_B", "B_inf") for c in range(3)]
    return report


def _resolution_reasons(value: float, config: IdentifiabilityConfig) -> list[str]:
    """Why a B_inf of `value` cannot be measured to the tolerance: the images round it to whole grey levels, which
    leaves up to half of one. The error is under what the images resolve, so the betas fitted with it keep their
    verdicts (unlike a B_inf the far end does not pin)."""
    half = 0.5 * config.grey_level / max(abs(value), 1e-6)
    if half <= config.tolerance:
        return []
    return [f"it is {value / config.grey_level:.1f} grey levels of the images, whose rounding alone leaves it "
            f"+-{half:.0%} (> {config.tolerance:.0%}): too faint to measure to the tolerance, and too faint to matter "
            "(under half a grey level of error)"]


def _drift_reasons(depth: float, config: IdentifiabilityConfig) -> list[str]:
    """Why a beta_D read over a span of `depth` optical depths is not pinned: a drift of the surfaces' colours with
    range that is not the water's (`color_drift`) moves it by about color_drift / depth."""
    shift = config.color_drift / max(depth, 1e-6)
    if shift <= config.tolerance:
        return []
    return [f"over {depth:.2f} optical depths a {config.color_drift:.0%} drift of the surfaces' colours with range "
            f"that is not the water's (texture blurring with distance) would move it by {shift:.0%} "
            f"(> {config.tolerance:.0%})"]


def _far_end_reasons(c: int, value: float, fit: MediumFit, report: IdentifiabilityReport,
                     config: IdentifiabilityConfig) -> list[str]:
    """Why a B_inf not read off open water (channel `c`, `value`) is not pinned by the far end of the ranges."""
    how = "read off the far end of the ranges" if fit.veil_below is not None else "fitted to the dark samples"
    lead = f"{how}, not off open water"
    if report.open_water_reason:
        lead += f" ({report.open_water_reason})"
    why = []
    t = report.far_transmission[c]
    if t > config.max_far_transmission:
        why.append(f"the far end (range {report.far_range:.2f}) still shows {t:.0%} of the surfaces' own signal "
                   f"(> {config.max_far_transmission:.0%}): the veiling light is not reached")
    if fit.veil_below is not None and fit.veil_above is not None:
        below, above = float(fit.veil_below[c]), float(fit.veil_above[c])
        half = abs(above - below) / 2 / max(abs(value), 1e-6)
        if half > config.far_end_tolerance:
            why.append(f"its two readings there (darkest surfaces {below:.3f}, median colour {above:.3f}) leave it "
                       f"+-{half:.0%} (> {config.far_end_tolerance:.0%})")
    else:
        gap = abs(report.far_color[c] - value) / max(abs(value), 1e-6)
        if gap > config.far_end_tolerance:
            why.append(f"the far end's median colour {report.far_color[c]:.3f} is {gap:.0%} from it "
                       f"(> {config.far_end_tolerance:.0%})")
    return [f"{lead}: {', '.join(why)}"] if why else []
