"""Datamanager `synthetic`: the built-in procedural underwater scene, generated on first use."""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import ClassVar

from uw3dgs.data.cache import default_cache_dir
from uw3dgs.data.datamanager import DataManagerConfig
from uw3dgs.data.dataparser import DataParser
from uw3dgs.data.downscale import downscale_scene
from uw3dgs.data.scene import SceneData
from uw3dgs.data.seathru_layout import read_seathru_layout
from uw3dgs.datamanagers.synthetic.config import SyntheticSceneConfig, cache_key
from uw3dgs.datamanagers.synthetic.scene import generate_scene
from uw3dgs.registry import DataManagerSpec
from uw3dgs.utils.io import atomic_folder


def cached_scene(config: SyntheticSceneConfig, cache_dir: Path) -> Path:
    """The folder of `config`'s scene, generating it first if needed (atomically: a killed generation
    leaves no half-written scene behind; when another process finished first, its scene is kept)."""
    target = cache_dir / "synthetic" / cache_key(config)
    if not (target / "gt" / "medium.json").is_file():
        with atomic_folder(target) as tmp:
            generate_scene(config, tmp)
    return target


class SyntheticDataParser(DataParser):
    """The built-in scene (generated into the cache on first use) or a folder written by `uw-synth`, read whole
    at full resolution (small images), then downscaled with `downscale_scene` (ground truth included)."""

    config: SyntheticDataManagerConfig

    def parse(self, data: Path | None, downscale_factor: int) -> SceneData:
        root = data if data is not None else cached_scene(self.config.scene,
                                                          self.config.cache_dir or default_cache_dir())
        scene = read_seathru_layout(Path(root))
        scene.name = "synthetic" if data is None else scene.name
        return downscale_scene(scene, downscale_factor)


@dataclass(frozen=True)
class SyntheticDataManagerConfig(DataManagerConfig):
    scene: SyntheticSceneConfig = field(default_factory=SyntheticSceneConfig)
    """The procedural scene (size, views, medium); each distinct setting is generated once and cached."""
    cache_dir: Path | None = None
    """Where generated scenes are kept; default $UW3DGS_CACHE or ~/.cache/uw3dgs."""
    parser: ClassVar[type[DataParser]] = SyntheticDataParser

    @classmethod
    def can_read(cls, path: Path) -> bool:
        """A folder written by `uw-synth`: the SeaThru-NeRF layout plus gt/medium.json."""
        return (path / "gt" / "medium.json").is_file()


datamanager = DataManagerSpec(
    "synthetic", "Built-in procedural underwater seabed with known clean radiance, depth and medium "
    "(or a folder written by uw-synth, via --data).", SyntheticDataManagerConfig())
