"""Volume rendering along sampled rays: the standard compositor and SeaThru-NeRF's underwater one.

Standard (NeRF): with alpha_i = 1 - exp(-sigma_i delta_i) and T_i = exp(-sum_{j<i} sigma_j delta_j),
    w_i = T_i alpha_i,   C = sum_i w_i c_i,   A = sum_i w_i.
Underwater (SeaThru-NeRF, their Eq. 22 and `compute_alpha_weights_uw`), per colour channel, at world distances
s_i from the camera and per-ray medium (sigma_attn, sigma_bs, c_med):
    C = sum_i w_i c_i exp(-sigma_attn s_i)
        + c_med [ (1 - exp(-sigma_bs s_0)) + sum_i T_i exp(-sigma_bs s_i) (1 - exp(-sigma_bs (s_{i+1} - s_i))) ]
with s_S = infinity: the water in front of the first sample (no object there, T = 1) and behind the last one count,
so a ray through empty water sees exactly c_med and a zero medium gives the standard image.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import Tensor


def volume_weights(sigma: Tensor, deltas: Tensor) -> tuple[Tensor, Tensor]:
    """(w [R, S], T [R, S]) of densities `sigma` [R, S] >= 0 over intervals `deltas` [R, S] (any unit the densities
    are per): T_i the transmittance before sample i, w_i = T_i (1 - exp(-sigma_i delta_i))."""
    optical = sigma * deltas
    before = torch.cumsum(optical, dim=-1) - optical  # exclusive: what lies in front of sample i
    trans = torch.exp(-before)
    return trans * -torch.expm1(-optical), trans


def composite(weights: Tensor, rgb: Tensor) -> tuple[Tensor, Tensor]:
    """(C [R, 3] = sum_i w_i c_i, A [R] = sum_i w_i) of weights [R, S] and colours `rgb` [R, S, 3]."""
    return (weights[..., None] * rgb).sum(dim=-2), weights.sum(dim=-1)


def beer_lambert(sigma: Tensor, distance: Tensor) -> Tensor:
    """exp(-sigma * distance) for `sigma` [R, 1, C] >= 0 and `distance` [R, S, 1] >= 0 possibly infinite: 0 at an
    infinite distance unless sigma is 0 (then 1), with finite gradients everywhere."""
    far = torch.isinf(distance)
    decay = torch.exp(-sigma * torch.where(far, torch.zeros_like(distance), distance))
    return torch.where(far, (sigma == 0).to(decay.dtype), decay)


@dataclass
class UnderwaterComposite:
    """Per ray: `rgb` [R, 3] the underwater colour, `direct` [R, 3] the attenuated object term, `backscatter` [R, 3]
    the medium term, `restored` [R, 3] = sum_i w_i c_i, the scene without water (SeaThru-NeRF's J)."""

    rgb: Tensor
    direct: Tensor
    backscatter: Tensor
    restored: Tensor


def composite_underwater(weights: Tensor, trans: Tensor, rgb: Tensor, ranges: Tensor, sigma_attn: Tensor,
                         sigma_bs: Tensor, c_med: Tensor) -> UnderwaterComposite:
    """SeaThru-NeRF's compositing (module docstring) of object weights w [R, S] and transmittances T [R, S]
    (`volume_weights`), colours `rgb` [R, S, 3], samples at world distances `ranges` [R, S] (non-decreasing, may be
    inf) and the medium of each ray: `sigma_attn`, `sigma_bs` [R, 3] >= 0 per unit of `ranges`, `c_med` [R, 3]."""
    s = ranges[..., None]
    s_next = torch.cat([s[:, 1:], torch.full_like(s[:, :1], float("inf"))], dim=1)
    attn = beer_lambert(sigma_attn[:, None], s)
    direct = (weights[..., None] * rgb * attn).sum(dim=1)
    bs_here, bs_next = beer_lambert(sigma_bs[:, None], s), beer_lambert(sigma_bs[:, None], s_next)
    front = 1.0 - bs_here[:, 0]
    water = front + (trans[..., None] * (bs_here - bs_next)).sum(dim=1)
    backscatter = c_med * water
    restored = (weights[..., None] * rgb).sum(dim=1)
    return UnderwaterComposite(direct + backscatter, direct, backscatter, restored)
