"""Datamanager base: loads a scene, splits it, and serves training and test views.

A datamanager plugin subclasses `DataManagerConfig` (its knobs) and `DataManager` (`load_scene`),
and registers a `DataManagerSpec` under the entry-point group `uw3dgs.datamanagers`.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from pathlib import Path
from typing import Any, ClassVar

import torch
import torch.nn.functional as F

from uw3dgs.cameras import Camera
from uw3dgs.config import InstantiateConfig, Target, target
from uw3dgs.data.covisibility import covisible_mask
from uw3dgs.data.scene import GroundTruth, SceneData

Batch = dict[str, Any]
"""One view: 'index', 'camera', 'image' [H, W, 3]; plus 'clean_image' and 'range' where known (and, for test
views, 'covisible')."""


@dataclass(frozen=True)
class DataManagerConfig(InstantiateConfig):
    _target: Target = target(lambda: DataManager)
    llffhold: int = 8
    """Every llffhold-th view (sorted by name, index % llffhold == 0) is held out for testing; 0 = none."""

    generic: ClassVar[bool] = False
    """A catch-all layout (e.g. any COLMAP folder): when a specific datamanager also reads `--data`, it wins."""

    @classmethod
    def can_read(cls, path: Path) -> bool:
        """Whether `path` looks like this datamanager's layout (used when `--data` is given)."""
        return False


def split_indices(num_views: int, llffhold: int) -> tuple[list[int], list[int]]:
    """The standard LLFF/SeaThru-NeRF split: test = index % llffhold == 0."""
    if llffhold <= 0:
        return list(range(num_views)), []
    test = [i for i in range(num_views) if i % llffhold == 0]
    train = [i for i in range(num_views) if i % llffhold != 0]
    return train, test


def downscale_scene(scene: SceneData, factor: int) -> SceneData:
    """Area-average images (and ground truth) by an integer factor and scale the intrinsics to match."""
    if factor == 1:
        return scene
    if factor < 1:
        raise ValueError(f"--downscale-factor must be a positive integer, got {factor}")

    def pool(x: torch.Tensor) -> torch.Tensor:  # [N, H, W, C] -> [N, H/f, W/f, C]
        return F.avg_pool2d(x.permute(0, 3, 1, 2), factor).permute(0, 2, 3, 1).contiguous()

    cameras = []
    for cam in scene.cameras:
        K = cam.K.clone()
        K[:2] /= factor  # with pixel-centre coordinates u + 0.5, cx and cy scale by the same factor
        cameras.append(Camera(cam.viewmat, K, cam.width // factor, cam.height // factor, cam.name))
    gt = None
    if scene.gt is not None:
        ranges = scene.gt.ranges.unsqueeze(-1)
        # open water (inf) must stay open water: pool a finite copy, then mark blocks with any inf
        finite = torch.where(torch.isfinite(ranges), ranges, torch.zeros_like(ranges))
        any_inf = pool((~torch.isfinite(ranges)).float()) > 0
        pooled = torch.where(any_inf, torch.full_like(any_inf, float("inf"), dtype=ranges.dtype), pool(finite))
        gt = GroundTruth(pool(scene.gt.clean_images), pooled.squeeze(-1), scene.gt.medium)
    return dataclasses.replace(scene, images=pool(scene.images), cameras=cameras, gt=gt)


class DataManager:
    """Serves one random training view per step (a fresh permutation each epoch, as 3DGS does)."""

    downscales_on_load: ClassVar[bool] = False
    """True when `load_scene` already returns the scene at 1/`self.downscale_factor` (e.g. through an image
    cache); the base class then leaves it as it is instead of downscaling it again."""

    def __init__(self, config: DataManagerConfig, data: Path | None, downscale_factor: int = 1,
                 device: str | torch.device = "cpu", seed: int = 0):
        if downscale_factor < 1:
            raise ValueError(f"--downscale-factor must be a positive integer, got {downscale_factor}")
        self.config = config
        self.data = data
        self.device = torch.device(device)
        self.downscale_factor = downscale_factor
        scene = self.load_scene(data)
        self.scene = scene if self.downscales_on_load else downscale_scene(scene, downscale_factor)
        self.train_indices, self.test_indices = split_indices(len(self.scene.image_names), config.llffhold)
        if not self.train_indices:
            raise ValueError(f"{data}: no training views left after holding out every {config.llffhold}-th view")
        self.images = self.scene.images.to(self.device)
        self.cameras = [c.to(self.device) for c in self.scene.cameras]
        self._generator = torch.Generator().manual_seed(seed)
        self._queue: list[int] = []
        self._covisible: dict[int, torch.Tensor] = {}

    def load_scene(self, data: Path | None) -> SceneData:
        raise NotImplementedError(f"{type(self).__name__} must implement load_scene()")

    @property
    def scene_name(self) -> str:
        return self.scene.name

    def get_batch(self, index: int) -> Batch:
        batch: Batch = {"index": index, "camera": self.cameras[index], "image": self.images[index]}
        if self.scene.gt is not None:
            batch["clean_image"] = self.scene.gt.clean_images[index].to(self.device)
            batch["range"] = self.scene.gt.ranges[index].to(self.device)
        return batch

    def next_train(self) -> Batch:
        if not self._queue:
            order = torch.randperm(len(self.train_indices), generator=self._generator).tolist()
            self._queue = [self.train_indices[i] for i in order]
        return self.get_batch(self._queue.pop())

    def test_batches(self):
        """Test views; with ground-truth ranges also 'covisible' [H, W], the pixels whose surface some training
        view has in its field of view (`covisible_mask`): metrics over them leave out what no model can know."""
        for index in self.test_indices:
            batch = self.get_batch(index)
            if "range" in batch:
                if index not in self._covisible:  # fixed by the split: computed at the first evaluation only
                    train_cameras = [self.cameras[i] for i in self.train_indices]
                    self._covisible[index] = covisible_mask(batch["camera"], batch["range"], train_cameras)
                batch["covisible"] = self._covisible[index]
            yield batch

    def state_dict(self) -> dict[str, Any]:
        """What a resumed run needs to draw the same views as an uninterrupted one."""
        return {"generator": self._generator.get_state(), "queue": list(self._queue)}

    def load_state_dict(self, state: dict[str, Any]) -> None:
        self._generator.set_state(state["generator"])
        self._queue = list(state["queue"])


@dataclass(frozen=True)
class AutoDataManagerConfig(DataManagerConfig):
    """Pick the datamanager from `--data`: the built-in synthetic scene without it, else the layout found."""

    def resolve(self, data: Path | None) -> DataManagerConfig:
        from uw3dgs.registry import DATAMANAGERS

        if data is None:
            chosen = DATAMANAGERS["synthetic"].config
        else:
            if not Path(data).exists():
                raise FileNotFoundError(f"--data {data} does not exist")
            found = [spec for _, spec in DATAMANAGERS.items() if type(spec.config).can_read(Path(data))]
            if not found:
                raise ValueError(f"--data {data}: no datamanager recognises this folder "
                                 f"(known: {', '.join(DATAMANAGERS)}); see the README's data layouts")
            if len(found) > 1 and sum(not type(s.config).generic for s in found) == 1:
                found = [s for s in found if not type(s.config).generic]
            if len(found) > 1:
                names = ", ".join(s.name for s in found)
                raise ValueError(f"--data {data} matches several datamanagers ({names}); name one after the "
                                 f"method, e.g. `uw-train 3dgs --data {data} {found[0].name}`")
            chosen = found[0].config
        return type(chosen)(**{**chosen.__dict__, "llffhold": self.llffhold})
