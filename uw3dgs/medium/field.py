"""The interface of a medium field, as the framework's commands see it: beta_D and beta_B readable anywhere in the
world, the veiling light B_inf, and a JSON summary for `uw-export` (`medium.json`)."""

from __future__ import annotations

from typing import Any

import torch
from torch import Tensor, nn

MEANING = ("Underwater image formation (Akkaynak-Treibitz, as UW-3DGS uses it): I = J exp(-beta_D z) + B_inf (1 - "
           "exp(-beta_B z)), z the range in dataset units. b_inf: RGB veiling light in [0, 1]. beta_d, beta_b: RGB "
           "coefficients per dataset unit. A grid medium: values at the points bounds_min + index / (shape - 1) x "
           "(bounds_max - bounds_min) of the dataset frame, indexed [i][j][k][channel] along x, y, z; outside the box "
           "the model reads the nearest border value.")

CONSTANT_TOLERANCE = 1e-5
"""A field whose sampled betas vary by at most this share of their largest value (float rounding) is written as one
value per channel."""


class Medium(nn.Module):
    """A medium field. Subclasses hold `b_inf` [3] (a parameter or buffer) and implement `betas`; one that varies in
    space returns its box from `box`, so its summary samples it there."""

    b_inf: Tensor

    def betas(self, x: Tensor) -> tuple[Tensor, Tensor]:
        """(beta_D, beta_B) at world points x [N, 3], each [N, 3], >= 0, per dataset unit."""
        raise NotImplementedError

    def ray_betas(self, origin: Tensor, dirs: Tensor, ranges: Tensor) -> tuple[Tensor, Tensor]:
        """Mean beta_D, beta_B [P, 3] along rays origin [3] + t dirs [P, 3], t in [0, ranges [P]] (world units).
        Default: the field at each ray's midpoint."""
        return self.betas(origin + dirs * (0.5 * ranges)[:, None])

    def box(self) -> tuple[Tensor, Tensor] | None:
        """(lo [3], hi [3]) in world units where the field varies; None for a medium that is the same everywhere."""
        return None

    @torch.no_grad()
    def summary(self, dataset_center: tuple[float, float, float], dataset_scale: float,
                samples: int) -> dict[str, Any]:
        """The medium as a JSON-ready dict in the dataset frame (`MEANING`): a homogeneous one as one value per
        channel; one with a box sampled at `samples` (>= 2) points per axis over it, unless its samples are one value
        everywhere (to CONSTANT_TOLERANCE), then as one value too."""
        data: dict[str, Any] = {"b_inf": [float(v) for v in self.b_inf.detach().cpu()], "meaning": MEANING}
        box = self.box()
        if box is None:
            beta_d, beta_b = self.betas(self.b_inf.detach().new_zeros(1, 3))
            data.update(kind="homogeneous", beta_d=[float(v) for v in beta_d[0].cpu()],
                        beta_b=[float(v) for v in beta_b[0].cpu()])
            return data
        lo, hi = (t.detach().cpu().float() for t in box)
        t = torch.linspace(0.0, 1.0, samples)
        axes = [lo[a] + t * (hi[a] - lo[a]) for a in range(3)]
        points = torch.stack(torch.meshgrid(*axes, indexing="ij"), dim=-1).reshape(-1, 3)  # world frame
        beta_d, beta_b = self.betas(points.to(self.b_inf.device))
        if all(float((b.max(0).values - b.min(0).values).max()) <= CONSTANT_TOLERANCE * float(b.abs().max())
               for b in (beta_d, beta_b)):  # a field that is one value everywhere (e.g. as started): written as one
            data.update(kind="homogeneous", beta_d=[float(v) for v in beta_d.mean(0).cpu()],
                        beta_b=[float(v) for v in beta_b.mean(0).cpu()])
            return data
        center = torch.tensor(dataset_center, dtype=torch.float64)
        data.update(kind="grid", shape=[samples] * 3,
                    bounds_min=[float(v) for v in lo.double() * dataset_scale + center],
                    bounds_max=[float(v) for v in hi.double() * dataset_scale + center],
                    beta_d=beta_d.cpu().reshape(samples, samples, samples, 3).tolist(),
                    beta_b=beta_b.cpu().reshape(samples, samples, samples, 3).tolist())
        return data
