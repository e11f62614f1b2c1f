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

B_inf read off open water is a measurement, not a fit: it is reported as identifiable.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass

import torch
from torch import Tensor

from uw3dgs.fields.medium_estimate import MediumFit, fit_medium

CHANNELS = "RGB"


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
    dark_samples: int
    """Backscatter samples the fit used."""
    dark_excess: list[float]
    """[3] the darkest surfaces' own signal at the median range, J' exp(-beta_D z50) / B_inf, from the residual fit
    (this one or the other): ~0 for black surfaces."""
    residual: list[float]
    """[3] the fitted residual term J' (0 where not used)."""
    tolerance: float
    resamples: int
    checks: list[ParameterCheck]

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
        out.append(f"ranges {z10:.2f}-{z90:.2f} (10-90%), {self.dark_samples} backscatter samples, "
                   f"open water {'in view' if self.open_water else 'not in view'}")
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


def assess_medium(point: Tensor, color: Tensor, z: Tensor, fit: MediumFit, b_inf: Tensor | None, bins: int,
                  share: float, residual: bool, tolerance: float = 0.15, resamples: int = 8, seed: int = 0,
                  steps: int = 100, max_observations: int = 20_000) -> IdentifiabilityReport:
    """The report for `fit` of observations color [M, 3] of points point [M] at ranges z [M] (dataset units), as
    `fit_medium` made it (`b_inf` [3] read off open water, or None; `bins`, `share`, `residual` as given to it).
    Each of the `resamples` bootstrap fits searches `steps` candidates over at most `max_observations`."""
    generator = torch.Generator().manual_seed(seed)
    other_fit = fit_medium(point, color, z, b_inf, bins, share, residual=not residual, steps=steps,
                           max_observations=max_observations)
    other, with_residual = other_fit.medium, fit if residual else other_fit
    fits = []
    for _ in range(resamples):
        ids, rows = bootstrap_observations(point, generator)
        fits.append(fit_medium(ids, color[rows], z[rows], b_inf, bins, share, residual=residual, steps=steps,
                               max_observations=max_observations).medium)
    z10, z90 = (float(q) for q in torch.quantile(z.double(), torch.tensor([0.1, 0.9], dtype=torch.float64)))
    z50 = float(z.double().median())
    excess = with_residual.residual * torch.exp(-with_residual.beta_d * z50) / with_residual.b_inf.clamp_min(1e-3)
    report = IdentifiabilityReport(
        range_span=(z10, z90),
        optical_depth_span={name: (beta * (z90 - z10)).tolist() for name, beta in (("beta_D", fit.beta_d),
                                                                                  ("beta_B", fit.beta_b))},
        open_water=b_inf is not None, dark_samples=len(fit.dark_z),
        dark_excess=excess.tolist(),
        residual=fit.residual.tolist(), tolerance=tolerance, resamples=resamples, checks=[])
    for k, name in enumerate(("beta_D", "beta_B", "B_inf")):
        values = torch.stack([f[k] for f in fits]).double()
        lo, hi = torch.quantile(values, torch.tensor([0.05, 0.95], dtype=torch.float64), dim=0)
        estimate = fit.medium[k].double()
        scale = estimate.abs().clamp_min(1e-6)
        spread = ((hi - lo) / 2 / scale).tolist()
        assumption = ((other[k].double() - estimate).abs() / scale).tolist()
        for c in range(3):
            measured = name == "B_inf" and b_inf is not None
            s, a = (0.0, 0.0) if measured else (spread[c], assumption[c])
            why = [f"bootstrap spread +-{s:.0%}"] if s > tolerance else []
            if a > tolerance:
                why.append(f"{a:.0%} off if the darkest surfaces are {'' if residual else 'not '}black")
            reason = f"{', '.join(why)} (> {tolerance:.0%}): {_reason(name, c, report)}" if why else ""
            report.checks.append(ParameterCheck(name, CHANNELS[c], float(estimate[c]), s, a, not why, reason))
    return report
