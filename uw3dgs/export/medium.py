"""The learned medium as JSON (`medium.json` beside an exported PLY): B_inf, and beta_D, beta_B sampled on a regular
grid over the medium's box in the dataset frame (a homogeneous medium: its one value per channel). The betas are per
dataset unit (1/m for a dataset in metres), as the model learns them."""

from __future__ import annotations

from typing import Any

import torch

from uw3dgs.fields.medium import MediumField, MediumGrid

MEANING = ("Underwater image formation (Akkaynak-Treibitz, as UW-3DGS uses it): I = J exp(-beta_D z) + B_inf (1 - "
           "exp(-beta_B z)), z the range in dataset units. b_inf: RGB veiling light in [0, 1]. beta_d, beta_b: RGB "
           "coefficients per dataset unit. A grid medium: values at the points bounds_min + index / (shape - 1) x "
           "(bounds_max - bounds_min) of the dataset frame, indexed [i][j][k][channel] along x, y, z; outside the box "
           "the model reads the nearest border value.")


@torch.no_grad()
def medium_summary(medium: MediumField, dataset_center: tuple[float, float, float], dataset_scale: float,
                   samples: int) -> dict[str, Any]:
    """The medium as a JSON-ready dict; a grid medium sampled at `samples` points per axis (>= 2, which the
    command checks before loading the run)."""
    data: dict[str, Any] = {"b_inf": [float(v) for v in medium.b_inf.detach().cpu()], "meaning": MEANING}
    if not isinstance(medium, MediumGrid):  # the same everywhere
        beta_d, beta_b = medium.betas(medium.b_inf.new_zeros(1, 3))
        data.update(kind="homogeneous", beta_d=[float(v) for v in beta_d[0].cpu()],
                    beta_b=[float(v) for v in beta_b[0].cpu()])
        return data
    lo, hi = medium.box_min.cpu(), medium.box_max.cpu()
    t = torch.linspace(0.0, 1.0, samples)
    axes = [lo[a] + t * (hi[a] - lo[a]) for a in range(3)]
    points = torch.stack(torch.meshgrid(*axes, indexing="ij"), dim=-1).reshape(-1, 3)  # world frame
    beta_d, beta_b = medium.betas(points.to(medium.box_min.device))
    center = torch.tensor(dataset_center, dtype=torch.float64)
    data.update(kind="grid", shape=[samples] * 3,
                bounds_min=[float(v) for v in lo.double() * dataset_scale + center],
                bounds_max=[float(v) for v in hi.double() * dataset_scale + center],
                beta_d=beta_d.cpu().reshape(samples, samples, samples, 3).tolist(),
                beta_b=beta_b.cpu().reshape(samples, samples, samples, 3).tolist())
    return data

