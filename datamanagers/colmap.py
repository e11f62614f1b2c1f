"""Datamanager `colmap`: any image folder posed by COLMAP.

    ROOT/images/     the images, named as in the model (subfolders allowed)
    ROOT/sparse/0/   COLMAP model: cameras (PINHOLE, SIMPLE_PINHOLE, SIMPLE_RADIAL, RADIAL or OPENCV),
                     images, points3D (.bin or .txt)

Distorted cameras are undistorted, images downscaled once into the image cache, and the scene normalised
(centred on the cameras, median point depth 1) unless `--datamanager.no-normalize`. It is the catch-all
layout: a more specific datamanager that also reads the folder (seathru-nerf, uwbundle) wins in 'auto'.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import ClassVar

from uw3dgs.data.colmap_dataset import normalize_scene, read_colmap_dataset
from uw3dgs.data.datamanager import DataManagerConfig
from uw3dgs.data.dataparser import DataParser
from uw3dgs.data.scene import SceneData
from uw3dgs.registry import DataManagerSpec


class ColmapDataParser(DataParser):
    """ROOT/images/ + ROOT/sparse/0/ through `read_colmap_dataset`: undistorted, and downscaled one image at a
    time while reading (through the image cache), then normalised unless --datamanager.no-normalize."""

    config: ColmapDataManagerConfig

    def parse(self, data: Path | None, downscale_factor: int) -> SceneData:
        if data is None:
            raise ValueError("the colmap datamanager needs --data: a folder with images/ and sparse/0/ "
                             "(see docs/datasets.md)")
        root = Path(data)
        scene = read_colmap_dataset(root, root / "images", root / "sparse" / "0", self.config.cache_dir,
                                    downscale_factor)
        return normalize_scene(scene) if self.config.normalize else scene


@dataclass(frozen=True)
class ColmapDataManagerConfig(DataManagerConfig):
    normalize: bool = True
    """Centre on the mean camera centre and scale so the median camera-to-point distance is 1 (recorded in
    the run's dataparser_transforms.json; near/far follow)."""
    cache_dir: Path | None = None
    """Where undistorted / downscaled images are cached; default $UW3DGS_CACHE or ~/.cache/uw3dgs."""
    parser: ClassVar[type[DataParser]] = ColmapDataParser
    generic: ClassVar[bool] = True

    @classmethod
    def can_read(cls, path: Path) -> bool:
        """images/ and sparse/0/."""
        return (path / "images").is_dir() and (path / "sparse" / "0").is_dir()


datamanager = DataManagerSpec(
    "colmap", "Any COLMAP-posed folder (images/ + sparse/0/): undistorted, downscaled and cached on first use, "
    "normalised.", ColmapDataManagerConfig())
