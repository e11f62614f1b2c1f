"""Rays of pixels: origins, unit directions and the view each comes from, computed as `Camera` computes them."""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import Tensor

from uw3dgs.cameras import Camera


@dataclass
class RayBundle:
    """N rays in the world frame: `origins` [N, 3], unit `directions` [N, 3], `camera_indices` [N] (the scene's
    view index each ray comes from; -1 for a camera that is no view of the scene)."""

    origins: Tensor
    directions: Tensor
    camera_indices: Tensor

    def __len__(self) -> int:
        return len(self.origins)

    def __getitem__(self, index: slice | Tensor) -> RayBundle:
        return RayBundle(self.origins[index], self.directions[index], self.camera_indices[index])


def pixel_directions(K: Tensor, viewmat: Tensor, pixels: Tensor, width: int) -> Tensor:
    """Unit world directions [N, 3] of the pixel centres `pixels` [N] (row-major indices v * width + u) of cameras
    with intrinsics `K` [N, 3, 3] and world-to-camera matrices `viewmat` [N, 4, 4]; the same numbers as
    `Camera.ray_directions` at those pixels."""
    u = (pixels % width).to(K.dtype) + 0.5
    v = torch.div(pixels, width, rounding_mode="floor").to(K.dtype) + 0.5
    x = (u - K[:, 0, 2]) / K[:, 0, 0]
    y = (v - K[:, 1, 2]) / K[:, 1, 1]
    d_cam = torch.stack([x, y, torch.ones_like(x)], dim=-1)
    d_world = torch.einsum("ni,nij->nj", d_cam, viewmat[:, :3, :3].to(K.dtype))  # R^T d, as row vectors
    return torch.nn.functional.normalize(d_world, dim=-1)


def camera_ray_bundle(camera: Camera, index: int = -1) -> RayBundle:
    """Every pixel's ray of `camera`, row-major ([H * W] rays), labelled with view `index`."""
    directions = camera.ray_directions().reshape(-1, 3)
    origins = camera.center.to(directions.dtype).expand_as(directions)
    indices = torch.full((len(directions),), index, dtype=torch.long, device=directions.device)
    return RayBundle(origins, directions, indices)
