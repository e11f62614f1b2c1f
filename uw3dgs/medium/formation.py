"""The underwater image formation (Akkaynak-Treibitz, as UW-3DGS uses it) and the viewer's water control on it.

    I = J exp(-beta_D z) + B_inf (1 - exp(-beta_B z))

J the water-free radiance (URI), z the range along each pixel's ray in dataset units. The water control changes the
medium at render time only:

    I_k = J exp(-k beta_D z) + B (alpha (1 - exp(-k beta_B z)) + (1 - alpha) [k > 0])

alpha the URI's coverage and B the chosen veiling light: k = 1 with the learned B_inf is the model's own image, k = 0
removes the water (open water, at infinite range, then goes dark too: I_0 = J, the URI); k > 1 is murkier water.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import Tensor


@dataclass(frozen=True)
class Water:
    """The water control: `k` >= 0 scales beta_D and beta_B; `b_inf` (RGB in [0, 1]) replaces the learned B_inf,
    None keeps it."""

    k: float = 1.0
    b_inf: tuple[float, float, float] | None = None


def form_underwater_image(radiance: Tensor, alpha: Tensor, ranges: Tensor, beta_d: Tensor, beta_b: Tensor,
                          b_inf: Tensor, dataset_scale: float) -> dict[str, Tensor]:
    """The formation model for one view: 'uwi', 'attenuation' exp(-beta_D z) and 'backscatter' [H, W, 3].

    radiance [H, W, 3] = sum_i w_i c_i (no background), alpha [H, W] its coverage, ranges [H, W] the
    expected range of the covered part (world units), beta_* [H, W, 3], b_inf [3]. Exponents use dataset units
    (range x dataset_scale). The uncovered part (1 - alpha) sees open water: no surface, so its backscatter has
    saturated to B_inf. (Taking it at the scene's far bound instead, B_inf (1 - exp(-beta_B z_far)), falls short of
    the veiling light that real open water shows when z_far is a few attenuation lengths, and then biases B_inf.)
    """
    z = ranges[..., None] * dataset_scale
    attenuation = torch.exp(-beta_d * z)
    # a (1 - e^(-beta_B z)) + (1 - a), the covered part's backscatter plus open water's, is 1 - a e^(-beta_B z)
    backscatter = b_inf * (1 - alpha[..., None] * torch.exp(-beta_b * z))
    return {"uwi": radiance * attenuation + backscatter, "attenuation": attenuation, "backscatter": backscatter}


def form_with_water(uri: Tensor, alpha: Tensor, ranges: Tensor, beta_d: Tensor, beta_b: Tensor, b_inf: Tensor,
                    dataset_scale: float, water: Water = Water()) -> dict[str, Tensor]:
    """The formation with the water control (see the module's docstring): 'uwi', 'attenuation', 'backscatter'
    [H, W, 3] from the arguments of `form_underwater_image`, with `water.b_inf` (when given) replacing `b_inf`.
    k = 1 with the learned B_inf is exactly `form_underwater_image`; k = 0 gives the URI."""
    if water.k < 0:
        raise ValueError(f"the water factor k must be >= 0, got {water.k}")
    if water.b_inf is not None:
        b_inf = torch.tensor(water.b_inf).to(b_inf)
    if water.k == 0:
        return {"uwi": uri, "attenuation": torch.ones_like(uri), "backscatter": torch.zeros_like(uri)}
    # k = 1 is the model's own image bit for bit: 1.0 * beta is beta exactly
    return form_underwater_image(uri, alpha, ranges, water.k * beta_d, water.k * beta_b, b_inf, dataset_scale)
