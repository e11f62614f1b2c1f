"""PAUP's per-Gaussian statistics from K nearby views: U_i, how unstable a Gaussian's rendering is across views,
and P_i, how implausible it is physically (paper Sec. 3.3, pinned in docs/methods/uw3dgs.md).

`observe_view` reads one no-gradient render; `combine_views` turns K observations into U and P:

    U_i = w_alpha Var_k(a_ik) + w_c (1/K) sum_k ||c_ik - mean_k c_ik||^2        (population variances over all K)
    P_i = mean over the views whose image holds i's centre of
          |r_k(p_ik) - d_ik| / median_k + w_att a_i (1 - mean_channels exp(-beta_D(x_i) d_ik))

with a_ik the effective opacity (mean blending weight over the pixels i touches in view k, 0 where it touches
none), c_ik its SH colour seen from view k, d_ik the distance from camera k to its centre, r_k(p_ik) the rendered
range at the pixel its centre projects to, median_k the view's median rendered range over covered pixels, a_i its
opacity, beta_D per dataset unit (distances converted with the scene's dataset scale), w_att = 1 in the paper.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import torch
from torch import Tensor


@dataclass
class ViewObservation:
    """One view's no-gradient render, per Gaussian (all [N])."""

    effective_opacity: Tensor
    """Mean blending weight over the pixels the Gaussian was blended into; 0 where it was blended into none."""
    colors: Tensor
    """[N, 3] its view-dependent colour seen from this view."""
    inside: Tensor
    """bool: its centre projects into the image, in front of the camera."""
    physics: Tensor
    """P_ik (valid where `inside`)."""


def observe_view(weight_sum: Tensor, pixel_count: Tensor, colors: Tensor, means2d: Tensor, radii: Tensor,
                 own_range: Tensor, surface_range: Tensor, alpha: Tensor, opacities: Tensor,
                 beta_d: Tensor | None, dataset_scale: float, coverage_eps: float,
                 attenuation_weight: float = 1.0) -> ViewObservation:
    """What one view says about every Gaussian.

    weight_sum, pixel_count [N]: the rasterizer's per-Gaussian sums over this view; colors [N, 3]; means2d [N, 2]
    pixels (pixel (u, v) spans [u, u + 1) x [v, v + 1)); radii [N] (0 = culled); own_range [N] world units from
    the camera centre to each centre; surface_range, alpha [H, W] the rendered range (world units) and coverage;
    opacities [N] in [0, 1]; beta_d [N, 3] beta_D at the centres per dataset unit (None: no medium, the
    attenuation term is 0); dataset_scale dataset units per world unit; pixels with alpha <= coverage_eps are
    open water and do not set the view's median range; attenuation_weight scales P's attenuation term."""
    count = pixel_count.to(weight_sum.dtype)
    effective = torch.where(pixel_count > 0, weight_sum / count.clamp_min(1), torch.zeros_like(weight_sum))
    height, width = surface_range.shape
    pix = means2d.detach().floor().long()
    inside = (radii > 0) & (pix[:, 0] >= 0) & (pix[:, 0] < width) & (pix[:, 1] >= 0) & (pix[:, 1] < height)
    covered = surface_range[alpha > coverage_eps]
    scale = (covered if covered.numel() else surface_range.reshape(-1)).median().clamp_min(1e-12)
    u, v = pix[:, 0].clamp(0, width - 1), pix[:, 1].clamp(0, height - 1)
    physics = (surface_range[v, u] - own_range).abs() / scale
    if beta_d is not None:
        transmitted = torch.exp(-beta_d * (own_range * dataset_scale)[:, None]).mean(-1)
        physics = physics + attenuation_weight * opacities * (1.0 - transmitted)
    return ViewObservation(effective, colors, inside, torch.where(inside, physics, torch.zeros_like(physics)))


def combine_views(views: Sequence[ViewObservation], opacity_weight: float,
                  color_weight: float) -> tuple[Tensor, Tensor, Tensor]:
    """(U [N], P [N], measured [N] bool) from K observations; `measured` = some view's image holds the centre
    (U and P of the other Gaussians are meaningless here and are not to be used)."""
    effective = torch.stack([v.effective_opacity for v in views])  # [K, N]
    colors = torch.stack([v.colors for v in views])  # [K, N, 3]
    inside = torch.stack([v.inside for v in views])
    physics = torch.stack([v.physics for v in views])
    color_var = (colors - colors.mean(0)).square().sum(-1).mean(0)
    u = opacity_weight * effective.var(0, unbiased=False) + color_weight * color_var
    seen_in = inside.sum(0)
    p = physics.sum(0) / seen_in.clamp_min(1)
    return u, p, seen_in > 0
