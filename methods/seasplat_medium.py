"""SeaSplat's medium (Yang et al. 2024): one beta_D, beta_B and B_inf per colour channel, applied in image space to the
rendered depth normalised per image, and the image formation that uses them.

It is a homogeneous medium like the project's `medium-homogeneous` (`fields/medium.py`: the same three RGB values
everywhere, the framework's `Medium` interface, the optimizer groups 'medium_beta' and 'medium_b_inf') with SeaSplat's
parameterisation, which differs: the betas are free parameters clamped at 0 in the formation (theirs: 1x1 convolution
weights, `AttenuateNetV3` and `BackscatterNetV2` in `deepseecolor/models.py`), not softplus ones, and B_inf is the
sigmoid of a free logit. Adam steps those parameters, so the parameterisation is part of what is learned. The betas are
per unit of normalised depth (0 = the nearest pixel of the image, 1 = the farthest), not per dataset unit.
"""

from __future__ import annotations

from typing import Any

import torch
from torch import Tensor, nn

from uw3dgs.medium.field import Medium

RGB = tuple[float, float, float]


def seasplat_formation(restored: Tensor, depth: Tensor, beta_d: Tensor, beta_b: Tensor,
                       b_inf: Tensor) -> dict[str, Tensor]:
    """I = clamp(J exp(-max(beta_D z, 0)) + B_inf (1 - exp(-max(beta_B z, 0))), 0, 1) for J = `restored` [H, W, 3],
    z = `depth` [H, W] (normalised per image), beta_D, beta_B, B_inf [3]. Returns 'uwi' I, 'direct' J exp(..),
    'attenuation' exp(-max(beta_D z, 0)) and 'backscatter' B_inf (1 - exp(-max(beta_B z, 0))), each [H, W, 3]."""
    z = depth[..., None]
    attenuation = torch.exp(-(beta_d * z).clamp_min(0.0))
    backscatter = b_inf * (1.0 - torch.exp(-(beta_b * z).clamp_min(0.0)))
    direct = restored * attenuation
    return {"uwi": (direct + backscatter).clamp(0.0, 1.0), "direct": direct, "attenuation": attenuation,
            "backscatter": backscatter}


class SeaSplatMedium(Medium):
    """beta_D, beta_B [3] (free, clamped at 0 where used) and B_inf = sigmoid(logit) [3], the same everywhere.

    `beta_b_init` None draws beta_B uniformly from [0, 1) with the torch RNG, as their `BackscatterNetV2`; B_inf's
    logit starts as a uniform [0, 1) draw too and is normally replaced by the learned background's when the medium
    starts (`start_from_background`)."""

    MEANING = ("SeaSplat's image formation: I = clamp(J exp(-max(beta_D z, 0)) + B_inf (1 - exp(-max(beta_B z, "
                      "0))), 0, 1), z the rendered camera-space depth normalised per image to [0, 1] (min-max). b_inf: "
                      "RGB veiling light in [0, 1]. beta_d, beta_b: RGB coefficients per unit of that normalised depth "
                      "(negative values act as 0), not per dataset unit.")
    """What `medium.json` (uw-export) says its values mean (`summary`)."""

    def __init__(self, beta_d_init: RGB, beta_b_init: RGB | None):
        super().__init__()
        self.beta_d = nn.Parameter(torch.tensor(beta_d_init, dtype=torch.float32))
        self.beta_b = nn.Parameter(torch.rand(3) if beta_b_init is None
                                   else torch.tensor(beta_b_init, dtype=torch.float32))
        self.b_inf_logit = nn.Parameter(torch.rand(3))

    @property
    def b_inf(self) -> Tensor:
        """The veiling light [3] in (0, 1)."""
        return torch.sigmoid(self.b_inf_logit)

    def betas(self, x: Tensor) -> tuple[Tensor, Tensor]:
        """(beta_D, beta_B) as `Medium` gives them, each [N, 3] for points x [N, 3] (the same everywhere;
        per unit of normalised depth, not clamped)."""
        shape = (x.shape[0], 3)
        return self.beta_d.expand(shape), self.beta_b.expand(shape)

    def param_groups(self) -> dict[str, list[nn.Parameter]]:
        return {"medium_beta": [self.beta_d, self.beta_b], "medium_b_inf": [self.b_inf_logit]}

    def summary(self, dataset_center: tuple[float, float, float], dataset_scale: float,
                samples: int) -> dict[str, Any]:
        """`Medium.summary` (kind 'homogeneous') with SeaSplat's formation as its meaning."""
        return {**super().summary(dataset_center, dataset_scale, samples), "meaning": self.MEANING}

    @torch.no_grad()
    def start_from_background(self, background_logit: Tensor) -> None:
        """B_inf := the learned background colour (their `bg_from_bs`: the logit is copied)."""
        self.b_inf_logit.copy_(background_logit.to(self.b_inf_logit))

    def form(self, restored: Tensor, depth: Tensor) -> dict[str, Tensor]:
        """`seasplat_formation` with this medium's values."""
        return seasplat_formation(restored, depth, self.beta_d, self.beta_b, self.b_inf)
