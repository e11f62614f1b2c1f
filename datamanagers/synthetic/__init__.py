"""Datamanager `synthetic`: the built-in procedural underwater scene, generated on first use."""

from __future__ import annotations

import os
import shutil
import tempfile
from dataclasses import dataclass, field
from pathlib import Path

from uw3dgs.config import Target, target
from uw3dgs.data.cache import default_cache_dir
from uw3dgs.data.datamanager import DataManager, DataManagerConfig
from uw3dgs.data.scene import SceneData
from uw3dgs.data.seathru_layout import read_seathru_layout
from uw3dgs.datamanagers.synthetic.scene import SyntheticSceneConfig, cache_key, generate_scene
from uw3dgs.registry import DataManagerSpec


@dataclass(frozen=True)
class SyntheticDataManagerConfig(DataManagerConfig):
    _target: Target = target(lambda: SyntheticDataManager)
    scene: SyntheticSceneConfig = field(default_factory=SyntheticSceneConfig)
    """The procedural scene (size, views, medium); each distinct setting is generated once and cached."""
    cache_dir: Path | None = None
    """Where generated scenes are kept; default $UW3DGS_CACHE or ~/.cache/uw3dgs."""

    @classmethod
    def can_read(cls, path: Path) -> bool:
        """A folder written by `uw-synth`: the SeaThru-NeRF layout plus gt/medium.json."""
        return (path / "gt" / "medium.json").is_file()


def cached_scene(config: SyntheticSceneConfig, cache_dir: Path) -> Path:
    """The folder of `config`'s scene, generating it first if needed (atomically: a killed generation
    leaves no half-written scene behind)."""
    target = cache_dir / "synthetic" / cache_key(config)
    if (target / "gt" / "medium.json").is_file():
        return target
    target.parent.mkdir(parents=True, exist_ok=True)
    tmp = Path(tempfile.mkdtemp(dir=target.parent, prefix=f".{target.name}-"))
    try:
        generate_scene(config, tmp)
        if target.exists():  # another process finished first
            shutil.rmtree(tmp)
        else:
            os.replace(tmp, target)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise
    return target


class SyntheticDataManager(DataManager):
    config: SyntheticDataManagerConfig

    def load_scene(self, data: Path | None) -> SceneData:
        if data is None:
            data = cached_scene(self.config.scene, self.config.cache_dir or default_cache_dir())
        scene = read_seathru_layout(Path(data))
        scene.name = "synthetic" if self.data is None else scene.name
        return scene


datamanager = DataManagerSpec(
    "synthetic", "Built-in procedural underwater seabed with known clean radiance, depth and medium "
    "(or a folder written by uw-synth, via --data).", SyntheticDataManagerConfig())
