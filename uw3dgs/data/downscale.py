"""The one downscaling rule of uw3dgs: `--downscale-factor F` shrinks images by averaging F x F blocks, and
the cameras follow (K[:2] / F, width // F, height // F).

Every reader goes through these functions: the caching readers (colmap, seathru-nerf, uwbundle) call
`area_downscale` and `downscale_intrinsics` one image at a time while reading, the others hand the whole
scene to `downscale_scene`. So `--downscale-factor 8` gives the same pixels and cameras whichever way a scene
is read. The factor itself is checked once, by the datamanager (`uw3dgs.data.datamanager.DataManager`).
"""

from __future__ import annotations

import dataclasses
from typing import TypeVar

import numpy as np
import torch
import torch.nn.functional as F

from uw3dgs.cameras import Camera
from uw3dgs.data.scene import GroundTruth, SceneData

IntrinsicsT = TypeVar("IntrinsicsT", torch.Tensor, np.ndarray)


class FactorTooLargeError(ValueError):
    """The factor leaves no pixel: an image is smaller than one F x F block. The datamanager turns this into
    the user's message (naming --downscale-factor); readers let it pass."""

    def __init__(self, factor: int, width: int, height: int):
        super().__init__(f"a {factor} x {factor} block is larger than a {width}x{height} image")
        self.factor, self.width, self.height = factor, width, height


def area_downscale(images: torch.Tensor, factor: int) -> torch.Tensor:
    """Mean of factor x factor blocks of [H, W, C] or [N, H, W, C] images; the last H % factor rows and
    W % factor columns drop (so the size is H // factor x W // factor, as `downscale_intrinsics` says)."""
    if factor == 1:
        return images
    height, width = images.shape[-3:-1]
    if factor > height or factor > width:
        raise FactorTooLargeError(factor, width, height)
    batch = images if images.dim() == 4 else images[None]
    pooled = F.avg_pool2d(batch.permute(0, 3, 1, 2), factor).permute(0, 2, 3, 1).contiguous()
    return pooled if images.dim() == 4 else pooled[0]


def downscale_intrinsics(K: IntrinsicsT, width: int, height: int, factor: int) -> tuple[IntrinsicsT, int, int]:
    """The camera of the area-downscaled image: (K with its first two rows / factor, width // factor,
    height // factor). K is a [3, 3] tensor or array, divided in its own dtype (a copy; K is not changed)."""
    K = K.clone() if isinstance(K, torch.Tensor) else K.copy()
    K[:2] /= factor  # with pixel-centre coordinates u + 0.5, cx and cy scale by the same factor
    return K, width // factor, height // factor


def downscale_camera(camera: Camera, factor: int) -> Camera:
    """`camera` for its image downscaled by `factor` (same pose and name)."""
    K, width, height = downscale_intrinsics(camera.K, camera.width, camera.height, factor)
    return Camera(camera.viewmat, K, width, height, camera.name)


def downscale_scene(scene: SceneData, factor: int) -> SceneData:
    """Area-average images (and ground truth) by an integer factor and scale the intrinsics to match: for
    readers that hold the full-resolution scene in memory anyway (small images, e.g. synthetic scenes)."""
    if factor == 1:
        return scene
    images = area_downscale(scene.images, factor)
    cameras = [downscale_camera(cam, factor) for cam in scene.cameras]
    gt = None
    if scene.gt is not None:
        ranges = scene.gt.ranges.unsqueeze(-1)
        # open water (inf) must stay open water: pool a finite copy, then mark blocks with any inf
        finite = torch.where(torch.isfinite(ranges), ranges, torch.zeros_like(ranges))
        any_inf = area_downscale((~torch.isfinite(ranges)).float(), factor) > 0
        pooled = torch.where(any_inf, torch.full_like(any_inf, float("inf"), dtype=ranges.dtype),
                             area_downscale(finite, factor))
        gt = GroundTruth(area_downscale(scene.gt.clean_images, factor), pooled.squeeze(-1), scene.gt.medium)
    return dataclasses.replace(scene, images=images, cameras=cameras, gt=gt)
