"""Whole images from a ray renderer, in chunks of rays, so evaluation and rendering see [H, W, ...] outputs as the
Gaussian models give them."""

from __future__ import annotations

from collections.abc import Callable

import torch
from torch import Tensor

from uw3dgs.cameras import Camera
from uw3dgs.raymarch.rays import RayBundle, camera_ray_bundle


def render_camera(camera: Camera, render_rays: Callable[[RayBundle], dict[str, Tensor]], chunk: int,
                  index: int = -1) -> dict[str, Tensor]:
    """Every pixel of `camera` through `render_rays` (a dict of per-ray tensors [N, ...]), `chunk` rays at a time;
    each output reshaped to [H, W, ...]."""
    rays = camera_ray_bundle(camera, index)
    parts: dict[str, list[Tensor]] = {}
    for start in range(0, len(rays), chunk):
        for name, value in render_rays(rays[start:start + chunk]).items():
            parts.setdefault(name, []).append(value)
    return {name: torch.cat(values).reshape(camera.height, camera.width, *values[0].shape[1:])
            for name, values in parts.items()}
