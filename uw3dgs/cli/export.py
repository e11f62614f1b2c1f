"""`uw-export RUN/config.yml --output scene.ply`: the trained Gaussians in the 3DGS PLY layout, in the dataset's own
frame (the water-free scene other 3DGS viewers load), and the learned medium as `scene.medium.json` beside it (named
after the PLY, so two exports into one folder keep their own medium; docs/export.md)."""

from __future__ import annotations

import sys
from dataclasses import dataclass
from pathlib import Path
from typing import Literal

import tyro

from uw3dgs.cli.errors import report_user_errors
from uw3dgs.utils.console import info, route_warnings


@dataclass(frozen=True)
class ExportArgs:
    load_config: tyro.conf.Positional[Path]
    """The run's config.yml."""
    output: Path = Path("scene.ply")
    """The PLY file to write."""
    format: Literal["ply"] = "ply"
    """The layout: ply (the 3DGS reference code's; docs/export.md)."""
    medium_output: Path | None = None
    """Where the learned medium goes (methods with a medium); default beside --output, named after it
    (scene.ply -> scene.medium.json)."""
    medium_samples: int = 16
    """Grid points per axis at which a grid medium's beta_D and beta_B are written."""
    step: int | None = None
    """Export the checkpoint of this step (one the run kept) instead of the latest."""


def medium_path_for(ply: Path) -> Path:
    """The default medium file of a PLY: beside it, named after it (scene.ply -> scene.medium.json)."""
    return ply.with_suffix(".medium.json")


def run_export(args: ExportArgs) -> tuple[Path, Path | None, int]:
    """Write the PLY (and its medium JSON); returns (PLY path, medium path or None, Gaussians written)."""
    from uw3dgs.engine.evaluator import load_trained
    from uw3dgs.export.ply import gaussian_rows, write_ply
    from uw3dgs.utils.io import unwritable_reason, write_json

    medium_path = args.medium_output or medium_path_for(args.output)
    for option, path in (("--output", args.output), ("--medium-output", medium_path)):
        problem = unwritable_reason(path)
        if problem is not None:  # before the run is loaded
            raise ValueError(f"{option} {path}: {problem}")
    if args.medium_samples < 2:
        raise ValueError(f"--medium-samples must be at least 2, got {args.medium_samples}")
    _, datamanager, model, checkpoint = load_trained(args.load_config, "cpu", step=args.step)
    gaussians = getattr(model, "gaussians", None)
    if gaussians is None:
        raise ValueError(f"{args.load_config}: a {type(model).__name__} has no Gaussians to export as a PLY; render "
                         "it with uw-render instead")
    scene = datamanager.scene
    rows = gaussian_rows(gaussians, scene.dataset_center, scene.dataset_scale)
    write_ply(args.output, rows)
    summary = model.export_medium(scene.dataset_center, scene.dataset_scale, args.medium_samples)
    if summary is None:
        return args.output, None, len(rows)
    write_json(medium_path, {"checkpoint": str(checkpoint), **summary})
    return args.output, medium_path, len(rows)


def entrypoint(argv: list[str] | None = None) -> None:
    argv = sys.argv[1:] if argv is None else argv
    route_warnings()
    args = tyro.cli(ExportArgs, args=argv, prog="uw-export",
                    description="Export a trained run's Gaussians as a 3DGS PLY (dataset frame) and its medium as "
                                "JSON.")
    ply, medium, count = report_user_errors(lambda: run_export(args))
    info(f"{count:,} Gaussians written to {ply}" + (f"; the medium to {medium}" if medium else
                                                     " (the method has no medium: no medium file)"))


if __name__ == "__main__":
    entrypoint()
