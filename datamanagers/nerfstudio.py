"""Datamanager `nerfstudio`: a folder with a nerfstudio / instant-ngp `transforms.json` (ns-process-data's output).

    ROOT/transforms.json   intrinsics (per file or per frame), OpenGL camera-to-world poses, optional split
                           (train_filenames, val_filenames, test_filenames) and ply_file_path
    ROOT/images/...        the images it names

Poses are converted to uw3dgs' OpenCV convention, OPENCV cameras undistorted, images downscaled once into the
image cache (all through `uw3dgs.data.colmap_dataset`), and the scene normalised unless
`--datamanager.no-normalize`. See `uw3dgs.datamanagers.transforms_json` for the file format and docs/datasets.md.
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from pathlib import Path
from typing import ClassVar, Literal

from uw3dgs.data.colmap_dataset import normalize_scene, scene_from_model
from uw3dgs.data.datamanager import DataManagerConfig
from uw3dgs.data.dataparser import DataParser
from uw3dgs.data.scene import SceneData
from uw3dgs.datamanagers.transforms_json import TRANSFORMS_FILE, random_points, read_transforms
from uw3dgs.options import check_number
from uw3dgs.registry import DataManagerSpec
from uw3dgs.utils.console import warn


class NerfstudioDataParser(DataParser):
    """ROOT/transforms.json through `read_transforms`, then the COLMAP reader's undistortion, downscaling and
    cache (`scene_from_model`); normalised unless --datamanager.no-normalize."""

    config: NerfstudioDataManagerConfig

    def parse(self, data: Path | None, downscale_factor: int) -> SceneData:
        if data is None:
            raise ValueError("the nerfstudio datamanager needs --data: a folder with transforms.json "
                             "(see docs/datasets.md)")
        root = Path(data)
        found = read_transforms(root)
        model = found.model
        if not found.has_points:
            warn(f"{root / TRANSFORMS_FILE}: no ply_file_path, so no initial points: starting from "
                 f"{self.config.random_points} random points inside the cameras' bounds (training needs more "
                 "steps than from SfM points; `uw-process-data` makes them)")
            points, colors = random_points(model.viewmats, self.config.random_points)
            model = replace(model, points=points, colors=colors)
        scene = scene_from_model(model, root.name, found.image_dir, self.config.cache_dir, downscale_factor,
                                 missing_hint=f"{root / TRANSFORMS_FILE} lists it: restore it, or remove its frame")
        if self.config.split == "file" and found.split is not None:
            scene = replace(scene, split=found.split)
        return normalize_scene(scene) if self.config.normalize else scene


@dataclass(frozen=True)
class NerfstudioDataManagerConfig(DataManagerConfig):
    split: Literal["file", "llffhold"] = "file"
    """'file': the split transforms.json carries (train_filenames; test_filenames, else val_filenames), when it
    has one; 'llffhold' (or a file without one): every llffhold-th view sorted by name is held out."""
    random_points: int = 20000
    """How many random initial points when transforms.json names no ply_file_path."""
    normalize: bool = True
    """Centre on the mean camera centre and scale so the median camera-to-point distance is 1 (recorded in
    the run's dataparser_transforms.json; near/far follow)."""
    cache_dir: Path | None = None
    """Where undistorted / downscaled images are cached; default $UW3DGS_CACHE or ~/.cache/uw3dgs."""
    parser: ClassVar[type[DataParser]] = NerfstudioDataParser

    def check_options(self) -> None:
        super().check_options()
        check_number(self, "random_points", ge=1, integer=True)

    @classmethod
    def can_read(cls, path: Path) -> bool:
        """ROOT/transforms.json."""
        return (path / TRANSFORMS_FILE).is_file()


datamanager = DataManagerSpec(
    "nerfstudio", "nerfstudio / instant-ngp folders (transforms.json): OpenGL poses converted, OPENCV cameras "
    "undistorted, downscaled and cached on first use, the file's split, normalised.", NerfstudioDataManagerConfig())
