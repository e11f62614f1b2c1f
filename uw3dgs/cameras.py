"""Pinhole cameras in the OpenCV/COLMAP convention (x right, y down, z forward)."""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import Tensor


@dataclass
class Camera:
    """One undistorted pinhole view.

    `viewmat` maps world to camera coordinates (4x4, COLMAP's world-to-camera pose);
    `K` is the 3x3 intrinsic matrix in pixels for an image of `width` x `height`.
    """

    viewmat: Tensor
    K: Tensor
    width: int
    height: int
    name: str = ""

    @property
    def center(self) -> Tensor:
        """Camera centre in world coordinates."""
        R, t = self.viewmat[:3, :3], self.viewmat[:3, 3]
        return -R.T @ t

    def to(self, device: torch.device | str) -> Camera:
        return Camera(self.viewmat.to(device), self.K.to(device), self.width, self.height, self.name)

    def camera_rays(self) -> Tensor:
        """K^-1 (u, v, 1) for every pixel centre (u + 0.5, v + 0.5), [H, W, 3] in camera coordinates."""
        device, dtype = self.K.device, self.K.dtype
        v, u = torch.meshgrid(
            torch.arange(self.height, device=device, dtype=dtype) + 0.5,
            torch.arange(self.width, device=device, dtype=dtype) + 0.5,
            indexing="ij",
        )
        x = (u - self.K[0, 2]) / self.K[0, 0]
        y = (v - self.K[1, 2]) / self.K[1, 1]
        return torch.stack([x, y, torch.ones_like(x)], dim=-1)

    def ray_norms(self) -> Tensor:
        """|K^-1 (u, v, 1)| per pixel centre, [H, W]: converts a z-depth to a distance along the ray."""
        return self.camera_rays().norm(dim=-1)

    def ray_directions(self) -> Tensor:
        """Unit world-space direction of every pixel centre's ray, [H, W, 3] (origin: `center`)."""
        d_world = self.camera_rays() @ self.viewmat[:3, :3].to(self.K.dtype)  # R^T d, as row vectors
        return torch.nn.functional.normalize(d_world, dim=-1)

    def project(self, points: Tensor, w: Tensor | float = 1.0) -> tuple[Tensor, Tensor]:
        """Pixel coordinates [P, 2] (u, v; pixel i spans [i, i + 1)) of homogeneous world points `points` [P, 3]
        with weight `w` ([P, 1] or a number: 1 = a point, 0 = a direction at infinity), and whether each lands
        in the image in front of the camera [P]. Computed in the dtype of `points`."""
        R, t, K = (x.to(points.dtype) for x in (self.viewmat[:3, :3], self.viewmat[:3, 3], self.K))
        p = points @ R.T + w * t
        z = p[:, 2]
        uv = p[:, :2] / z.clamp_min(1e-12)[:, None] @ K[:2, :2].T + K[:2, 2]
        inside = (z > 1e-12) & (uv[:, 0] >= 0) & (uv[:, 0] < self.width) & (uv[:, 1] >= 0) & (uv[:, 1] < self.height)
        return uv, inside
