"""Datamanager `seathru-nerf`: real scenes of the SeaThru-NeRF dataset (Levy et al., CVPR 2023).

    ROOT/Images_wb/ (or images_wb/)  the images (white-balanced PNGs)
    ROOT/sparse/0/                   COLMAP model (OPENCV camera: undistorted on load)
    ROOT/poses_bounds.npy            LLFF poses and near/far bounds

Either pose source may be missing; when both are present they are compared (`--datamanager.poses`).
Images are undistorted and downscaled once into the image cache (see `uw3dgs.data.colmap_dataset`) and
the scene is normalised (centred on the cameras, median point depth 1) unless
`--datamanager.no-normalize`. See docs/datasets.md.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import ClassVar

from uw3dgs.data.colmap_dataset import normalize_scene
from uw3dgs.data.datamanager import DataManagerConfig
from uw3dgs.data.dataparser import DataParser
from uw3dgs.data.scene import SceneData
from uw3dgs.data.seathru_layout import IMAGE_DIRS, PoseSource, read_seathru_scene
from uw3dgs.registry import DataManagerSpec


class SeathruNerfDataParser(DataParser):
    """A SeaThru-NeRF scene folder through `read_seathru_scene`: pose source chosen, undistorted, and downscaled
    one image at a time while reading (through the image cache), then normalised unless
    --datamanager.no-normalize."""

    config: SeathruNerfDataManagerConfig

    def parse(self, data: Path | None, downscale_factor: int) -> SceneData:
        if data is None:
            raise ValueError("the seathru-nerf datamanager needs --data: a scene folder with Images_wb/ and "
                             "sparse/0/ or poses_bounds.npy (see docs/datasets.md)")
        scene = read_seathru_scene(Path(data), self.config.poses, self.config.cache_dir, downscale_factor)
        return normalize_scene(scene) if self.config.normalize else scene


@dataclass(frozen=True)
class SeathruNerfDataManagerConfig(DataManagerConfig):
    poses: PoseSource = "auto"
    """Pose source: 'colmap' (sparse/0), 'llff' (poses_bounds.npy), or 'auto': the one present; with both,
    COLMAP's if they agree, else the one the coloured SfM points fit clearly better (with a warning)."""
    normalize: bool = True
    """Centre on the mean camera centre and scale so the median camera-to-point distance is 1 (recorded in
    the run's dataparser_transforms.json; near/far follow)."""
    cache_dir: Path | None = None
    """Where undistorted / downscaled images are cached; default $UW3DGS_CACHE or ~/.cache/uw3dgs."""
    parser: ClassVar[type[DataParser]] = SeathruNerfDataParser

    @classmethod
    def can_read(cls, path: Path) -> bool:
        """Images_wb/ (or images_wb/) and a pose source, but no gt/medium.json (that is a synthetic scene)."""
        has_images = any((path / name).is_dir() for name in IMAGE_DIRS)
        has_poses = (path / "sparse" / "0").is_dir() or (path / "poses_bounds.npy").is_file()
        return has_images and has_poses and not (path / "gt" / "medium.json").is_file()


datamanager = DataManagerSpec(
    "seathru-nerf", "SeaThru-NeRF scenes (Images_wb/ + sparse/0 and/or poses_bounds.npy): undistorted, "
    "downscaled and cached on first use, normalised.", SeathruNerfDataManagerConfig())
