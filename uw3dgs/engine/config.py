"""The top-level config of a training run: what `uw-train METHOD` parses and `config.yml` stores.

Option names follow nerfstudio's where it has one (--max-num-iterations, --steps-per-save, ...).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Annotated, Literal

import tyro

from uw3dgs.data.datamanager import AutoDataManagerConfig, DataManagerConfig
from uw3dgs.engine.optimizers import ParamGroupConfig
from uw3dgs.models.base import ModelConfig
from uw3dgs.options import CheckedConfig, OptionError, check_number

SEED_LIMIT = 2**64
"""Seeds are below this: torch's generators take 64-bit seeds."""


def datamanager_choices() -> type:
    """The datamanager subcommands: 'auto' plus every registered datamanager (entry points included)."""
    from uw3dgs.registry import DATAMANAGERS

    defaults = {"auto": AutoDataManagerConfig()}
    descriptions = {"auto": "Built-in synthetic scene without --data, else the layout found in --data."}
    for name, spec in DATAMANAGERS.items():
        defaults[name] = spec.config
        descriptions[name] = spec.description
    return tyro.extras.subcommand_type_from_defaults(defaults, descriptions, prefix_names=False)


@dataclass(frozen=True)
class TrainConfig(CheckedConfig):
    method_name: tyro.conf.Suppress[str]
    """Registry name of the method; set by the subcommand."""
    model: ModelConfig
    """The method's model (scene representation, rendering, losses)."""
    optimizers: dict[str, ParamGroupConfig]
    """Learning rate and schedule per parameter group of the model."""
    data: Path | None = None
    """Dataset folder; without it, the built-in synthetic underwater scene (generated on first use)."""
    downscale_factor: int = 1
    """Integer factor to shrink the dataset's images by (intrinsics follow)."""
    output_dir: Path = Path("outputs")
    """Runs are written to OUTPUT_DIR/EXPERIMENT_NAME/METHOD/TIMESTAMP/."""
    experiment_name: str | None = None
    """Defaults to the scene's name."""
    timestamp: str = "{timestamp}"
    """Run folder name; '{timestamp}' becomes the current date and time."""
    load_config: Path | None = None
    """Start from a saved config.yml; options given on the command line override it."""
    resume: bool = False
    """Continue the run of --load-config (or of --timestamp) from its latest checkpoint."""
    max_num_iterations: int = 30000
    """Training steps (one image per step)."""
    steps_per_log: int = 10
    """Steps between TensorBoard scalar logs."""
    steps_per_save: int = 2000
    """Steps between checkpoints (the last step is always saved)."""
    steps_per_eval_image: int = 500
    """Steps between rendering one test view to TensorBoard."""
    steps_per_eval_all_images: int = 5000
    """Steps between evaluating all test views (metrics to TensorBoard); the last step always evaluates."""
    keep_checkpoints: int = 2
    """How many recent checkpoints to keep on disk."""
    seed: int = 0
    """Seeds view order, initialisation noise and densification sampling."""
    device: Literal["auto", "cpu", "cuda"] = "auto"
    """'auto' uses CUDA when available."""
    progress: bool = True
    """Show the rich progress bar."""
    viewer: bool = False
    """Show the model live in the browser while it trains (http://VIEWER_HOST:VIEWER_PORT, docs/viewer.md); its
    renders (without gradient) take at most 5% of the wall time and leave the training's numbers unchanged."""
    viewer_port: int = 7007
    """Port of --viewer's web server."""
    viewer_host: str = "127.0.0.1"
    """Address --viewer listens on; 127.0.0.1 is this machine only (reach it from elsewhere with ssh -L)."""
    datamanager: Annotated[DataManagerConfig, tyro.conf.arg(constructor_factory=datamanager_choices)] = field(
        default_factory=AutoDataManagerConfig)
    """Which dataset reader; a subcommand after the options (default: auto)."""

    def check_options(self) -> None:
        for name in ("max_num_iterations", "steps_per_log", "steps_per_save", "steps_per_eval_image",
                     "steps_per_eval_all_images", "keep_checkpoints", "downscale_factor"):
            check_number(self, name, ge=1, integer=True)
        check_number(self, "viewer_port", ge=1, le=65535, integer=True)
        if not (isinstance(self.seed, int) and 0 <= self.seed < SEED_LIMIT):  # what torch's generators take
            raise OptionError("seed", f"must be a whole number from 0 to 2**64 - 1, got {self.seed}")
        for name in ("timestamp", "experiment_name"):
            value = getattr(self, name)
            if value is not None and (not isinstance(value, str) or value in ("", ".", "..") or "/" in value
                                      or "\\" in value):
                raise OptionError(name, f"must be one folder name (no '/', not empty, '.' or '..'), got {value!r}")
