"""A loaded scene: images, cameras and initial points, whatever the on-disk layout was."""

from __future__ import annotations

from dataclasses import dataclass, field

import torch
from torch import Tensor

from uw3dgs.cameras import Camera


@dataclass
class GroundTruth:
    """What only a synthetic scene knows: clean radiance, true ranges and the true medium."""

    clean_images: Tensor
    """[N, H, W, 3] water-free radiance in [0, 1]."""
    ranges: Tensor
    """[N, H, W] distance along each pixel's ray to the surface; inf where the ray sees open water."""
    medium: dict = field(default_factory=dict)
    """Contents of gt/medium.json (beta_D, beta_B, B_inf per channel, units)."""

    def medium_tensors(self) -> tuple[Tensor, Tensor, Tensor]:
        """(beta_D, beta_B, B_inf) of the homogeneous true medium, each [3] float32."""
        return tuple(torch.tensor(self.medium[k], dtype=torch.float32) for k in ("beta_D", "beta_B", "B_inf"))


@dataclass
class SceneData:
    """All views of one scene in memory, in one world frame (OpenCV camera convention)."""

    name: str
    image_names: list[str]
    images: Tensor
    """[N, H, W, 3] float32 in [0, 1], rows follow `image_names` (sorted)."""
    cameras: list[Camera]
    points: Tensor
    """[P, 3] initial points (SfM or synthetic) in world units."""
    point_colors: Tensor
    """[P, 3] their colours in [0, 1]."""
    near: float
    far: float
    """Depth bounds of the scene along the rays, in world units."""
    gt: GroundTruth | None = None
    dataset_center: tuple[float, float, float] = (0.0, 0.0, 0.0)
    dataset_scale: float = 1.0
    """Scene normalisation: world = (dataset - dataset_center) / dataset_scale. A distance d in world
    units is d * dataset_scale dataset units (the medium's beta is per dataset unit)."""
    gt_points: Tensor | None = None
    """[M, 3] ground-truth surface points (UWBundle's groundtruth.ply) for geometry evaluation, in the
    ground-truth file's own frame and units: not the world frame (see docs/uwbundle.md)."""
    split: tuple[list[int], list[int]] | None = None
    """(train, test) view indices the dataset itself names (e.g. transforms.json's train_filenames); None: the
    datamanager holds out every llffhold-th view."""


def scene_extent(cameras: list[Camera]) -> float:
    """3DGS's 'cameras extent': 1.1 x the largest distance of a camera centre from their mean.

    Position learning rates and size thresholds are relative to it, so a scene in millimetres trains
    like one in metres.
    """
    centers = torch.stack([c.center for c in cameras]).double()
    radius = (centers - centers.mean(dim=0)).norm(dim=-1).max().item()
    return 1.1 * max(radius, 1e-6)
