"""Is there water at all? A plain verdict on a medium from its optical depth over the scene's ranges.

The water's whole effect on a pixel at range z is set by the optical depths beta_D z and beta_B z: the direct
signal keeps exp(-beta_D z) of the surface's colour and the backscatter is B_inf (1 - exp(-beta_B z)), at most
beta_B z (B_inf <= 1). When both optical depths stay below a level tau in every channel out to the far end of the
ranges the surfaces are seen at, the water changes no pixel by more than about tau: the scene has little or no
water, and the water-free render (URI) equals the underwater one (UWI) within that. A medium fitted to such a scene
is noise (small, never exactly 0), and learning it lets the medium stand in for surfaces (a veiling light the colour
of a wall), so uw3dgs then renders without one (docs/evaluation.md, "The water verdict", has the measurement).

The verdict is made before training from the starting estimate (`methods/uw3dgs/model.py`) and, where that sees
water, from an upper bound on the multi-view fit (how the colour of one surface changes with its range across views,
the direct evidence: none on a dry scene, whatever the single image suggests); uw-eval makes it again from the
learned medium; all are kept in the run folder (`notes/water.json`) and in uw-eval's JSON.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import Tensor

CHANNELS = "RGB"
FAR_QUANTILE = 0.95
"""The 'far end' of the ranges: this quantile of the observations' ranges (the farthest few are often outliers)."""


@dataclass(frozen=True)
class WaterVerdict:
    """Optical depths of a medium at the far end of a scene's ranges, and what they mean."""

    depth_d: tuple[float, float, float]
    """beta_D z_far per channel (R, G, B)."""
    depth_b: tuple[float, float, float]
    """beta_B z_far per channel."""
    far_range: float
    """z_far in dataset units."""
    level: float
    """tau: the optical depth below which, in every channel, the scene counts as having little or no water."""
    source: str = "the single-image estimate"
    """Which medium was judged (the estimate before training, a bound from the multi-view fit, the learned one)."""

    @property
    def little_water(self) -> bool:
        return max(*self.depth_d, *self.depth_b) < self.level

    def line(self) -> str:
        """One line for any scene (surfaces, not seabed): the verdict and its numbers."""
        depth = ", ".join(f"{c} {d:.3f}/{b:.3f}" for c, d, b in zip(CHANNELS, self.depth_d, self.depth_b,
                                                                        strict=True))
        numbers = (f"optical depth beta_D*z/beta_B*z at the far surfaces ({self.far_range:.3g} dataset units) of "
                   f"{self.source}: {depth}")
        if self.little_water:
            return (f"little or no water: {numbers}, below {self.level:g} in every channel; the URI equals the UWI "
                    "within noise; consider 3dgs")
        return f"water: {numbers} (little or no water would be below {self.level:g} in every channel)"

    def to_json(self) -> dict:
        return {"little_water": self.little_water, "depth_d": list(self.depth_d), "depth_b": list(self.depth_b),
                "far_range": self.far_range, "level": self.level, "source": self.source, "line": self.line()}


def far_range(ranges: Tensor, quantile: float = FAR_QUANTILE) -> float:
    """The `quantile` of `ranges` [M] (dataset units): how far the surfaces the views see reach."""
    if ranges.numel() == 0:
        raise ValueError("no observation ranges to judge the water by")
    return float(torch.quantile(ranges.double().flatten()[:2**24], quantile))


def water_verdict(beta_d: Tensor, beta_b: Tensor, z_far: float, level: float,
                  source: str = "the single-image estimate") -> WaterVerdict:
    """The verdict on a homogeneous medium (beta_d, beta_b [3], per dataset unit) over ranges up to `z_far`; `source`
    names that medium in the verdict's line."""
    depth_d = tuple(float(x) * z_far for x in beta_d.detach().double().cpu().tolist())
    depth_b = tuple(float(x) * z_far for x in beta_b.detach().double().cpu().tolist())
    return WaterVerdict(depth_d, depth_b, float(z_far), float(level), source)  # type: ignore[arg-type]
