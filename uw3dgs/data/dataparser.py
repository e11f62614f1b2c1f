"""Dataparser base: one on-disk format -> one `SceneData` (as nerfstudio separates dataparsers from datamanagers).

A dataparser only reads. Splitting the views, the order they are served in, batches and resumable state
belong to the one `uw3dgs.data.datamanager.DataManager`, which asks the parser for the scene. A data plugin
is a `DataManagerConfig` subclass (its options, `can_read`) that names its `DataParser` subclass in the
ClassVar `parser`; see docs/datasets.md, "Writing a data plugin".
"""

from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING

from uw3dgs.data.scene import SceneData

if TYPE_CHECKING:
    from uw3dgs.data.datamanager import DataManagerConfig


class DataParser:
    """Reads one on-disk format into a `SceneData`; `config` is the plugin's datamanager config (its options).

    Contract of `parse(data, downscale_factor)`:

    - `data` is the `--data` folder, or None when the user gave none (a parser that needs one raises an
      error saying what to pass);
    - `downscale_factor` is a positive integer, already checked by the datamanager;
    - the scene returned is at 1/downscale_factor resolution with the intrinsics already rescaled: images
      [N, H // f, W // f, 3] and each camera's K[:2] / f, width // f, height // f. One rule does that
      (`uw3dgs.data.downscale`: area average over f x f blocks):

      * readers that hold the whole full-resolution scene in memory anyway (small images, e.g. the synthetic
        scenes) read it, then return `downscale_scene(scene, downscale_factor)`;
      * readers of real captures (colmap, seathru-nerf, uwbundle) downscale while reading, one image at a
        time (`area_downscale` and `downscale_intrinsics`), so that a dive of 4K frames never sits in
        memory at full resolution, and their on-disk image cache holds the small images it serves.

    - views are sorted by image name (the test split, index % llffhold == 0, relies on it);
    - every problem with the input raises FileNotFoundError or ValueError with a message that names the file
      and the fix (`uw-train` shows it without a traceback).
    """

    def __init__(self, config: DataManagerConfig):
        self.config = config

    def parse(self, data: Path | None, downscale_factor: int) -> SceneData:
        raise NotImplementedError(f"{type(self).__name__} must implement parse(data, downscale_factor)")
