"""The datamanager: splits one scene and serves its training and test views, whatever format it came from.

A data plugin does not subclass `DataManager`. It defines a `DataManagerConfig` subclass (its options, the
layouts it recognises) that names its `uw3dgs.data.dataparser.DataParser` subclass (the reader of its format)
in the ClassVar `parser`, and registers a `DataManagerSpec` under the entry-point group `uw3dgs.datamanagers`.
`config.setup(data=..., downscale_factor=..., device=..., seed=...)` builds the one `DataManager`, which asks the
parser for the scene. See docs/datasets.md, "Writing a data plugin".
"""

from __future__ import annotations

from dataclasses import dataclass
from numbers import Integral
from pathlib import Path
from typing import Any, ClassVar

import torch

from uw3dgs.config import InstantiateConfig, Target, target
from uw3dgs.data.covisibility import covisible_mask
from uw3dgs.data.dataparser import DataParser
from uw3dgs.data.downscale import FactorTooLargeError
from uw3dgs.data.scene import SceneData
from uw3dgs.options import check_number

Batch = dict[str, Any]
"""One view: 'index', 'camera', 'image' [H, W, 3]; plus 'clean_image' and 'range' where known (and, for test
views, 'covisible')."""


@dataclass(frozen=True)
class DataManagerConfig(InstantiateConfig):
    """A data plugin's options. `setup(data=..., downscale_factor=..., device=..., seed=...)` builds the
    `DataManager`, which reads the scene with a `parser(config)`."""

    _target: Target = target(lambda: DataManager)
    llffhold: int = 8
    """Every llffhold-th view (sorted by name, index % llffhold == 0) is held out for testing; 0 = none."""

    parser: ClassVar[type[DataParser] | None] = None
    """The plugin's reader (a `DataParser` subclass). A class attribute, not a field: neither a command-line
    option nor written to config.yml."""
    generic: ClassVar[bool] = False
    """A catch-all layout (e.g. any COLMAP folder): when a specific datamanager also reads `--data`, it wins."""

    @classmethod
    def can_read(cls, path: Path) -> bool:
        """Whether `path` looks like this datamanager's layout (used when `--data` is given)."""
        return False

    def check_options(self) -> None:
        super().check_options()
        check_number(self, "llffhold", ge=0, integer=True)

    def make_parser(self) -> DataParser:
        """The parser that reads this plugin's format, configured by this config."""
        if self.parser is None:
            raise TypeError(f"{type(self).__name__} names no parser: a data plugin's config sets the class "
                            "attribute `parser = MyDataParser` (a uw3dgs.data.dataparser.DataParser subclass)")
        return self.parser(self)


def split_indices(num_views: int, llffhold: int) -> tuple[list[int], list[int]]:
    """The standard LLFF/SeaThru-NeRF split: test = index % llffhold == 0."""
    if llffhold <= 0:
        return list(range(num_views)), []
    test = [i for i in range(num_views) if i % llffhold == 0]
    train = [i for i in range(num_views) if i % llffhold != 0]
    return train, test


class DataManager:
    """Serves the views of one scene, whatever its format: the split, one random training view per step (a fresh
    permutation each epoch, as 3DGS does, from its own generator), test views, and the state a resumed run needs.

    The scene comes from the config's parser (`config.make_parser().parse(data, downscale_factor)`); this is
    the one place where `--downscale-factor` is checked.
    """

    def __init__(self, config: DataManagerConfig, data: Path | None, downscale_factor: int = 1,
                 device: str | torch.device = "cpu", seed: int = 0):
        if isinstance(downscale_factor, bool) or not isinstance(downscale_factor, Integral) or downscale_factor < 1:
            raise ValueError(f"--downscale-factor must be a positive integer, got {downscale_factor}")
        downscale_factor = int(downscale_factor)
        self.config = config
        self.data = data
        self.device = torch.device(device)
        self.downscale_factor = downscale_factor
        self.parser = config.make_parser()
        try:
            self.scene = self.parser.parse(data, downscale_factor)
        except FactorTooLargeError as err:
            raise ValueError(f"--downscale-factor {downscale_factor} is larger than the images "
                             f"({err.width}x{err.height} pixels{f' in {data}' if data is not None else ''}): "
                             f"choose a factor of at most {min(err.width, err.height)}") from err
        check_scene(self.scene, type(self.parser).__name__)
        if self.scene.split is not None:
            self.train_indices, self.test_indices = (list(s) for s in self.scene.split)
            if not self.train_indices:
                raise ValueError(f"{data}: the split the dataset names has no training view")
        else:
            self.train_indices, self.test_indices = split_indices(len(self.scene.image_names), config.llffhold)
            if not self.train_indices:
                raise ValueError(f"{data}: no training views left after holding out every {config.llffhold}-th "
                                 "view")
        self.images = self.scene.images.to(self.device)
        self.cameras = [c.to(self.device) for c in self.scene.cameras]
        self._generator = torch.Generator().manual_seed(seed)
        self._queue: list[int] = []
        self._covisible: dict[int, torch.Tensor] = {}
        self._seed = seed
        self._rays: Any = None
        """The `RayBatcher` of `next_train_rays`, made at its first call (views-only methods never have one)."""

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

    def next_train_rays(self, num_rays: int) -> Batch:
        """`num_rays` random rays across the training views, for ray-marching methods (uw3dgs/raymarch/ray_batches.py):
        'rays' (origins, unit directions, view indices), 'image' [N, 3] their pixels' colours, 'pixels' [N]; the
        same images, cameras and split as `next_train`."""
        return self._ray_batcher().next(num_rays)

    def _ray_batcher(self) -> Any:
        if self._rays is None:
            from uw3dgs.raymarch.ray_batches import RayBatcher

            self._rays = RayBatcher(self.images, self.cameras, self.train_indices, self._seed)
        return self._rays

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
        state = {"generator": self._generator.get_state(), "queue": list(self._queue)}
        if self._rays is not None:
            state["rays"] = self._rays.state_dict()
        return state

    def load_state_dict(self, state: dict[str, Any]) -> None:
        self._generator.set_state(state["generator"])
        self._queue = list(state["queue"])
        if "rays" in state:
            self._ray_batcher().load_state_dict(state["rays"])


def check_scene(scene: SceneData, parser: str) -> None:
    """What every parser must return: one image per name and camera, each camera the size of the images (so a
    parser that forgot to downscale, or to rescale its intrinsics, fails here rather than in the renderer)."""
    num = len(scene.image_names)
    if scene.images.dim() != 4 or len(scene.images) != num or len(scene.cameras) != num:
        raise ValueError(f"{parser} returned {len(scene.image_names)} image names, images of shape "
                         f"{tuple(scene.images.shape)} and {len(scene.cameras)} cameras; a DataParser returns one "
                         "[H, W, 3] image and one camera per name")
    height, width = scene.images.shape[1:3]
    for cam in scene.cameras:
        if (cam.width, cam.height) != (width, height):
            raise ValueError(f"{parser} returned {width}x{height} images but camera '{cam.name}' is "
                             f"{cam.width}x{cam.height}; a DataParser returns the scene at 1/downscale_factor with "
                             "the intrinsics rescaled (uw3dgs.data.downscale.downscale_scene does both)")


@dataclass(frozen=True)
class AutoDataManagerConfig(DataManagerConfig):
    """Pick the datamanager from `--data`: the built-in synthetic scene without it, else the layout found."""

    def setup(self, **kwargs: Any) -> Any:
        """The datamanager of the config `resolve` picks (the trainer resolves first, to record the choice)."""
        return self.resolve(kwargs.get("data")).setup(**kwargs)

    def resolve(self, data: Path | None) -> DataManagerConfig:
        from uw3dgs.registry import DATAMANAGERS

        if data is None:
            chosen = DATAMANAGERS["synthetic"].config
        else:
            if not Path(data).exists():
                raise FileNotFoundError(f"--data {data} does not exist")
            found = [spec for _, spec in DATAMANAGERS.items() if type(spec.config).can_read(Path(data))]
            if not found:
                raise ValueError(unrecognised_folder_message(Path(data), list(DATAMANAGERS)))
            if len(found) > 1 and sum(not type(s.config).generic for s in found) == 1:
                found = [s for s in found if not type(s.config).generic]
            if len(found) > 1:
                names = ", ".join(s.name for s in found)
                raise ValueError(f"--data {data} matches several datamanagers ({names}); name one after the "
                                 f"method, e.g. `uw-train 3dgs --data {data} {found[0].name}`")
            chosen = found[0].config
        return type(chosen)(**{**chosen.__dict__, "llffhold": self.llffhold})


def unrecognised_folder_message(data: Path, known: list[str]) -> str:
    """The one-line error for a --data folder no datamanager reads; a plain folder of images gets the command
    that poses it."""
    from uw3dgs.data.seathru_layout import IMAGE_SUFFIXES

    has_images = data.is_dir() and any(p.suffix.lower() in IMAGE_SUFFIXES for p in data.iterdir() if p.is_file())
    if has_images or (data / "images").is_dir():
        images = data if has_images else data / "images"
        return (f"--data {data}: images without camera poses; pose them first with `uw-process-data --images "
                f"{images} --out DIR`, then `uw-train ... --data DIR`")
    return (f"--data {data}: no datamanager recognises this folder (known: {', '.join(known)}); see the README's "
            "data layouts")
