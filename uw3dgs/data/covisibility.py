"""Which pixels of a test view the training views could have taught a model at all.

A test view at the end of a camera path sees some surface no training camera has in its field of view;
a model can only guess there, and PSNR over the whole image mixes that guess with reconstruction. The
co-visibility mask keeps the pixels whose surface lies inside at least one training view, as DyCheck's
masked PSNR does (Gao et al., "Monocular Dynamic View Synthesis: A Reality Check", 2022). It needs the
surface each pixel sees, so only datasets with ground-truth ranges (the synthetic scenes) have it.
"""

from __future__ import annotations

import torch
from torch import Tensor

from uw3dgs.cameras import Camera


def covisible_mask(camera: Camera, ranges: Tensor, others: list[Camera]) -> Tensor:
    """[H, W] bool: True where the surface `camera`'s pixel sees lies in front of and inside the image of at
    least one of `others` (field of view only: occlusion is not tested).

    `ranges` [H, W] is the distance along each pixel's ray to the surface, inf for open water: such a pixel
    sees a direction, not a point, and counts where another camera's view holds that direction.
    """
    dirs = camera.ray_directions().reshape(-1, 3).double()
    r = ranges.reshape(-1).double().to(dirs.device)
    finite = torch.isfinite(r)
    # homogeneous coordinates: the point centre + r d (w = 1), or the direction d itself at infinity (w = 0)
    xyz = torch.where(finite[:, None], camera.center.double() + dirs * torch.where(finite, r, 0.0)[:, None], dirs)
    w = finite.double()[:, None]
    seen = torch.zeros(len(r), dtype=torch.bool, device=dirs.device)
    for other in others:
        seen |= other.project(xyz, w)[1]
    return seen.view(camera.height, camera.width)
