"""`uw-synth --out DIR [--width 128 --num-views 32 ...]`: write the built-in synthetic underwater scene.

The folder is in the SeaThru-NeRF layout plus gt/, so `uw-train METHOD --data DIR` trains on it and
the evaluation can score clean radiance, depth and the recovered medium against the truth.
"""

from __future__ import annotations

import time
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import tyro
from rich.console import Console
from rich.table import Table

from uw3dgs.cli.errors import exit_with_error
from uw3dgs.datamanagers.synthetic.config import SyntheticSceneConfig
from uw3dgs.datamanagers.synthetic.rendering import medium_parameters
from uw3dgs.datamanagers.synthetic.scene import generate_scene
from uw3dgs.options import check_config, deferred_checks
from uw3dgs.utils.console import info
from uw3dgs.utils.io import describe_os_error, unwritable_reason


@dataclass(frozen=True)
class SynthArgs:
    """Write the built-in synthetic underwater scene (procedural seabed, known medium) to a folder."""

    out: Path
    """Folder to write the scene into; it must be new or empty."""
    scene: tyro.conf.OmitArgPrefixes[SyntheticSceneConfig] = field(default_factory=SyntheticSceneConfig)
    """The scene's knobs, as flat flags (--width, --num-views, --medium-strength, ...)."""


def _rgb(values: np.ndarray) -> str:
    return "(" + ", ".join(f"{v:.3f}" for v in values) + ")"


def summary(config: SyntheticSceneConfig, out: Path, seconds: float) -> Table:
    """What was written: views, size, medium and ground-truth depth statistics."""
    ranges = np.stack([np.load(p) for p in sorted((out / "gt" / "range").glob("*.npy"))])
    finite = ranges[np.isfinite(ranges)]
    medium = medium_parameters(config)
    disk = sum(p.stat().st_size for p in out.rglob("*") if p.is_file())
    table = Table(title=f"Synthetic underwater scene written in {seconds:.1f} s", show_header=False)
    rows = [
        ("views", f"{config.num_views} ({config.path} path), {config.width}x{config.height} px, "
                  f"{config.fov_deg:g} deg horizontal FOV"),
        ("beta_D (1/m)", _rgb(medium["beta_D"])),
        ("beta_B (1/m)", _rgb(medium["beta_B"])),
        ("B_inf", _rgb(medium["B_inf"])),
        ("range (m)", f"{finite.min():.2f} .. {finite.max():.2f} (median {np.median(finite):.2f})"),
        ("open water", f"{100 * np.isinf(ranges).mean():.1f}% of pixels"),
        ("points", f"{config.num_points} in sparse/0/points3D.bin"),
        ("where", f"{out} ({disk / 2**20:.1f} MiB)"),
    ]
    if config.water_type is not None:
        rows.insert(1, ("water type", f"Jerlov {config.water_type}: beta_D = beta_B = K_d (Jerlov 1976), "
                                      "B_inf from b / (a + b) (Solonenko & Mobley 2015)"))
    if config.medium_profile != "homogeneous":
        where = "at the seabed" if config.medium_profile == "turbid-bottom" else "at the plume's centre"
        rows.insert(-1, ("medium profile", f"{config.medium_profile}: beta up to {1 + config.medium_profile_gain:g}x "
                                           f"the values above ({where}); see gt/medium.json"))
    if config.marine_snow > 0:
        rows.insert(-1, ("marine snow", f"{config.marine_snow} particles per view, in Images_wb/ only "
                                        "(listed in gt/marine_snow.json)"))
    for key, value in rows:
        table.add_row(key, value)
    return table


def entrypoint(argv: Sequence[str] | None = None) -> None:
    console = Console()
    try:
        with deferred_checks():  # the scene's checks run below, naming the option as typed (--medium-strength)
            args = tyro.cli(SynthArgs, args=argv, prog="uw-synth")
        check_config(args.scene)
        problem = unwritable_reason(args.out, folder=True)
        if problem is not None:
            raise ValueError(f"--out {args.out}: {problem}")
    except ValueError as exc:
        exit_with_error(exc, console)
    start = time.perf_counter()
    try:
        generate_scene(args.scene, args.out)
    except ValueError as exc:  # impossible settings, e.g. cameras under the seabed
        exit_with_error(exc, console)
    except OSError as exc:  # a folder that became unwritable, a full disk
        exit_with_error(exc, console, message=describe_os_error(exc))
    console.print(summary(args.scene, args.out, time.perf_counter() - start))  # the result, on stdout
    info(f"train on it with: uw-train uw3dgs --data {args.out}")


if __name__ == "__main__":
    entrypoint()
