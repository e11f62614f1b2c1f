"""The medium a run starts from, each parameter taken from the evidence that pins it (`--model.medium.init
multiview`).

Two estimates read the same water from different evidence:
- the single-image estimate (fields/medium_estimate.py): B_inf off open water (a measurement) or the far end of the
  ranges, beta_B off the darkest pixels, taken as black; its identifiability report
  (fields/medium_identifiability.py) says where those assumptions hold;
- the multi-view estimate (fields/medium_multiview.py): how each point's colour changes over its ranges; its
  bootstrap and span counts say where the ranges differ enough.

Per channel: B_inf off open water is held (in the multi-view fit too); else the multi-view B_inf where it is
identified by range diversity, else the single-image one (identified by the far end of the ranges, or not
identified). The multi-view fit is then made with B_inf held where it did not come from it, so the betas of a
channel are fitted with the B_inf used. Each beta is taken from the estimate that identifies it, the one with the
smaller spread where both do; where neither does, it is reported as not identified and starts from the value with
the smaller spread (the multi-view bootstrap's against the single-image report's spread or assumption; the
single-image value where the medium varies, the channel's B_inf is not identified, or, for beta_D, the multi-view
beta_B is not). Betas fitted with a B_inf that nothing identifies are not identified by range diversity either.

Where either estimate finds the halves of the scene disagreeing (a medium that varies in space: a homogeneous value
is an average), the betas come from the multi-view field fit (fields/medium_varying.py) where its bootstrap pins
every beta and B_inf, reported as identified by range diversity, varying in space (B_inf fitted with the field,
even where open water seemed in view; `EvidenceReport.factor` is then the field's factor); else no beta is
identified.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Callable
from dataclasses import asdict, dataclass, field

import torch
from torch import Tensor

from uw3dgs.fields.medium_estimate import MediumEstimate
from uw3dgs.fields.medium_identifiability import IdentifiabilityReport
from uw3dgs.fields.medium_multiview import CHANNELS, PARAMETERS, MultiviewEstimate
from uw3dgs.fields.medium_varying import FactorField

RANGE_DIVERSITY = "range diversity"
VARYING = "range diversity, varying in space"
OPEN_WATER = "open water"
DARK_PIXELS = "dark pixels"
FAR_END = "the far end of the ranges"
NOT_IDENTIFIED = "not identified"


@dataclass
class EvidenceCheck:
    name: str
    channel: str
    value: float
    source: str
    """Which evidence identifies it: RANGE_DIVERSITY, VARYING (a beta of the field fit: its value where the factor
    is 1), OPEN_WATER, DARK_PIXELS, FAR_END, or NOT_IDENTIFIED."""
    single: float
    """The single-image estimate's value."""
    multiview: float
    """The multi-view estimate's value (NaN: no fit)."""
    reason: str = ""
    """Why neither estimate identifies it (empty otherwise)."""


@dataclass
class EvidenceReport:
    checks: list[EvidenceCheck] = field(default_factory=list)
    multiview_lines: list[str] = field(default_factory=list)
    factor: FactorField | None = None
    """The betas' factor across the scene where they come from the field fit (source VARYING): beta(x) = the
    value x factor(x); None: a homogeneous medium."""

    def value(self, name: str) -> Tensor:
        return torch.tensor([c.value for c in self.checks if c.name == name], dtype=torch.float32)

    @property
    def medium(self) -> tuple[Tensor, Tensor, Tensor]:
        return self.value("beta_D"), self.value("beta_B"), self.value("B_inf")

    def lines(self) -> list[str]:
        out = []
        for name in PARAMETERS:
            checks = [c for c in self.checks if c.name == name]
            parts = ", ".join(f"{c.channel} {c.value:.3f} by {c.source}" if c.source != NOT_IDENTIFIED
                              else f"{c.channel} {c.value:.3f} not identified ({c.reason})" for c in checks)
            out.append(f"{name}: {parts}")
        return out

    def to_json(self) -> dict:
        out = asdict(self)
        out["factor"] = None if self.factor is None else self.factor.to_json()
        return out


def _single_verdict(report: IdentifiabilityReport | None, name: str, c: int) -> tuple[bool, float, str]:
    """(identifiable, uncertainty as a share of the value, reason) of the single-image report's check."""
    if report is None:
        return False, math.inf, "no identifiability report (--model.medium.report off)"
    check = next(x for x in report.checks if x.name == name and x.channel == CHANNELS[c])
    return check.identifiable, max(check.spread, check.assumption), check.reason


def combine_by_evidence(single: MediumEstimate, report: IdentifiabilityReport | None, open_water: Tensor | None,
                        fit_multiview: Callable[[Tensor | None], MultiviewEstimate]) -> EvidenceReport:
    """The combined medium (module doc). `fit_multiview(b_inf)` runs the multi-view estimate with B_inf [3] held
    where not NaN (None: all free) and returns a `MultiviewEstimate`; `open_water` [3] is the B_inf read off open
    water (None: none in view)."""
    values = dict(zip(PARAMETERS, (single.beta_d, single.beta_b, single.b_inf), strict=True))
    free = fit_multiview(None if open_water is None else open_water.double())
    b_inf, b_source, b_reason = [], [], []
    for c in range(3):
        multi = free.check("B_inf", c)
        ok, _, why = _single_verdict(report, "B_inf", c)
        if open_water is not None:
            b_inf.append(float(open_water[c]))
            b_source.append(OPEN_WATER)
            b_reason.append("")
        elif multi.identified:
            b_inf.append(multi.value)
            b_source.append(RANGE_DIVERSITY)
            b_reason.append("")
        else:
            b_inf.append(float(values["B_inf"][c]))
            b_source.append(FAR_END if ok else NOT_IDENTIFIED)
            b_reason.append("" if ok else f"multi-view: {multi.reason}; single image: {why}")
    hold = torch.tensor([v if s != RANGE_DIVERSITY else math.nan for v, s in zip(b_inf, b_source, strict=True)],
                        dtype=torch.float64)
    multiview: MultiviewEstimate = free if bool(hold.isnan().all()) or (
        open_water is not None and bool((hold == open_water.double()).all())) else fit_multiview(hold)
    result = EvidenceReport(multiview_lines=multiview.lines())
    varies = bool(getattr(report, "varies_in_space", False)) or free.varies_in_space or multiview.varies_in_space
    field_fit = multiview.varying
    if varies and field_fit is not None and field_fit.all_betas_identified and all(field_fit.identified["B_inf"]):
        result.factor = field_fit.fit.factor  # B_inf too: the field fit's, fitted with it (even over open water)
        b_inf, b_source, b_reason = field_fit.fit.b_inf.tolist(), [VARYING] * 3, [""] * 3
    for name in PARAMETERS:
        for c in range(3):
            multi = multiview.check(name, c)
            single_value = float(values[name][c])
            if name == "B_inf":
                result.checks.append(EvidenceCheck(name, CHANNELS[c], b_inf[c], b_source[c], single_value,
                                                   multi.value, b_reason[c]))
                continue
            ok, uncertainty, why = _single_verdict(report, name, c)
            if result.factor is not None:  # the field fit pins every beta: its value where the factor is 1
                value = float((field_fit.fit.beta_d if name == "beta_D" else field_fit.fit.beta_b)[c])
                result.checks.append(EvidenceCheck(name, CHANNELS[c], value, VARYING, single_value, multi.value))
                continue
            if varies:  # a homogeneous value is an average, whichever estimate it comes from
                fitted = "" if field_fit is None else ", and the field fit's bootstrap does not pin every beta"
                multi = dataclasses.replace(multi, identified=False, reason="the halves of the scene disagree: the "
                                            f"medium varies in space{fitted}")
                ok, why = False, multi.reason
            if b_source[c] == NOT_IDENTIFIED:  # the multi-view betas were fitted with a B_inf nothing pins
                multi = dataclasses.replace(multi, identified=False,
                                            reason=f"fitted with B_inf held at {b_inf[c]:.3f}, which is not identified")
            if multi.identified and (not ok or multi.spread <= uncertainty):
                check = EvidenceCheck(name, CHANNELS[c], multi.value, RANGE_DIVERSITY, single_value, multi.value)
            elif ok:
                check = EvidenceCheck(name, CHANNELS[c], single_value, DARK_PIXELS, single_value, multi.value)
            else:  # neither pins it: start from the one with the smaller spread (flagged either way)
                # a beta_D fitted under a beta_B the fit does not pin has a spread that says nothing of it
                pinned = name != "beta_D" or multiview.check("beta_B", c).identified
                closer = not varies and pinned and b_source[c] != NOT_IDENTIFIED and math.isfinite(multi.spread) \
                    and multi.spread < uncertainty
                start = f"; started from the multi-view value (spread +-{multi.spread:.0%} against the single " \
                        f"image's +-{uncertainty:.0%})" if closer else ""
                check = EvidenceCheck(name, CHANNELS[c], multi.value if closer else single_value, NOT_IDENTIFIED,
                                      single_value, multi.value, f"multi-view: {multi.reason}; single image: {why}"
                                      f"{start}")
            result.checks.append(check)
    return result
