"""Floaters: big Gaussians hanging in front of the surface, measured over the training views.

`floater_ratio` is the share of ALL Gaussians that are big (largest scale above BIG_SCALE_FACTOR x the median
largest scale over all Gaussians) and float: in at least VIEW_SHARE of the training views that see them, the
centre's range is below (1 - FRONT_MARGIN) x the surface range at the pixel it projects to. A view sees
Gaussian i when its centre projects inside the image, in front of the camera, and the rasterizer blended it into
at least one pixel (pixel_count > 0, radii > 0). A Gaussian no view sees does not float (it stays in the
denominator). The surface is the rendered range (`floater_ratio`) or the true one (`floater_ratio_gt`, where
the scene has true ranges). docs/evaluation.md, "Floater ratio", says why and where it falls short.

The three constants below are the definition, not knobs: changing them makes a different metric.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping, Sequence
from typing import Any

import torch
from torch import Tensor

from uw3dgs.cameras import Camera

BIG_SCALE_FACTOR = 2.0
"""A Gaussian is big when its largest scale is above this times the median largest scale over all Gaussians."""
FRONT_MARGIN = 0.1
"""A Gaussian floats in a view when its centre's range is below (1 - FRONT_MARGIN) x the surface range at the
pixel its centre projects to: more than 10% of its range in front of the surface."""
VIEW_SHARE = 0.5
"""A big Gaussian is a floater when it floats in at least this share of the training views that see it."""


def seen_in_view(means2d: Tensor, radii: Tensor, pixel_count: Tensor, in_front: Tensor, width: int,
                 height: int) -> tuple[Tensor, Tensor]:
    """Where each Gaussian's centre lands in one view and whether the view sees it.

    means2d [N, 2] projected centres in pixels (pixel (u, v) has its centre at (u + 0.5, v + 0.5)); radii [N] and
    pixel_count [N] as the rasterizer returns them; in_front [N] bool, the centre in front of the camera. Returns
    (pixels [N, 2] long (u, v) = floor(means2d), seen [N] bool: the centre's pixel is in the width x height image,
    in front of the camera, and the Gaussian was blended into at least one pixel)."""
    pixels = means2d.detach().floor().long()
    inside = (pixels[:, 0] >= 0) & (pixels[:, 0] < width) & (pixels[:, 1] >= 0) & (pixels[:, 1] < height)
    return pixels, inside & in_front & (radii > 0) & (pixel_count > 0)


def floating_in_view(own_range: Tensor, pixels: Tensor, seen: Tensor, surface: Tensor) -> Tensor:
    """Which Gaussians one view sees floating, [N] bool.

    own_range [N]: distance of each centre from the camera centre (world units); pixels [N, 2] long (u, v) the
    pixel of each centre; seen [N] bool (`seen_in_view`); surface [H, W] the surface range along each pixel's
    ray (same units; inf = no surface). True where seen and own_range < (1 - FRONT_MARGIN) x surface[v, u]."""
    height, width = surface.shape
    u = pixels[:, 0].clamp(0, width - 1)  # unseen centres may lie outside the image: read anything, masked below
    v = pixels[:, 1].clamp(0, height - 1)
    at_pixel = surface.to(own_range.device, torch.float64)[v, u]
    return seen & (own_range.double() < (1.0 - FRONT_MARGIN) * at_pixel)


def floater_ratio(max_scale: Tensor, floating_votes: Tensor, seen_votes: Tensor) -> float | None:
    """Share of all N Gaussians that are big and floating (None for N = 0: no share to give).

    max_scale [N]: each Gaussian's largest scale (world units); floating_votes [N], seen_votes [N]: in how many
    views it floats, and how many views see it. Big: max_scale > BIG_SCALE_FACTOR x median(max_scale) (torch's
    median: the lower middle value for an even N). Floating: seen by at least one view and floating in at least
    VIEW_SHARE of the views that see it."""
    n = len(max_scale)
    if n == 0:
        return None
    return float(floaters(max_scale, floating_votes, seen_votes).sum()) / n


def floaters(max_scale: Tensor, floating_votes: Tensor, seen_votes: Tensor) -> Tensor:
    """[N] bool: the Gaussians `floater_ratio` counts (big and floating; arguments as there, N >= 1)."""
    big = max_scale > BIG_SCALE_FACTOR * max_scale.median()
    return big & (seen_votes > 0) & (floating_votes >= VIEW_SHARE * seen_votes)


def floater_votes(means: Tensor, cameras: Sequence[Camera], render: Callable[[Camera], Mapping[str, Any]],
                  true_ranges: Sequence[Tensor] | None = None) -> dict[str, Tensor]:
    """Count, per Gaussian, the views that see it and those where it floats.

    means [N, 3] centres (world units); cameras: the views (on the device of `means`); render(camera) gives 'range'
    [H, W] (the rendered surface range; the far bound where nothing covers), 'means2d' [N, 2], 'radii' [N] and
    'pixel_count' [N]; true_ranges: per camera the true range map [H, W] (inf = open water), or None. Returns
    'seen' [N] long, 'floating' [N] long against the rendered surface and, with true ranges, 'floating_gt' [N]."""
    means = means.detach()
    seen_votes = torch.zeros(len(means), dtype=torch.long, device=means.device)
    votes = {"seen": seen_votes, "floating": torch.zeros_like(seen_votes)}
    if true_ranges is not None:
        votes["floating_gt"] = torch.zeros_like(seen_votes)
    for k, camera in enumerate(cameras):
        out = render(camera)
        R, t = camera.viewmat[:3, :3].to(means.dtype), camera.viewmat[:3, 3].to(means.dtype)
        in_front = (means @ R.T + t)[:, 2] > 0
        pixels, seen = seen_in_view(out["means2d"], out["radii"], out["pixel_count"], in_front, camera.width,
                                    camera.height)
        own_range = (means - camera.center.to(means.dtype)).norm(dim=-1)
        votes["seen"] += seen.long()
        votes["floating"] += floating_in_view(own_range, pixels, seen, out["range"].detach()).long()
        if true_ranges is not None:
            votes["floating_gt"] += floating_in_view(own_range, pixels, seen, true_ranges[k]).long()
    return votes


def floater_ratios(means: Tensor, max_scale: Tensor, cameras: Sequence[Camera],
                   render: Callable[[Camera], Mapping[str, Any]],
                   true_ranges: Sequence[Tensor] | None = None) -> dict[str, float | None]:
    """'floater_ratio' over `cameras` (the training views) and, with their true range maps, 'floater_ratio_gt'.

    Arguments as `floater_votes`, plus max_scale [N] each Gaussian's largest scale (world units)."""
    votes = floater_votes(means, cameras, render, true_ranges)
    ratios = {"floater_ratio": floater_ratio(max_scale, votes["floating"], votes["seen"])}
    if true_ranges is not None:
        ratios["floater_ratio_gt"] = floater_ratio(max_scale, votes["floating_gt"], votes["seen"])
    return ratios
