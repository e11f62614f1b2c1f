"""`uw-eval CONFIG.yml`: render the test views of a trained run and write its metrics as JSON."""

from __future__ import annotations

import sys
from dataclasses import dataclass
from pathlib import Path

import tyro
from rich.console import Console
from rich.table import Table

from uw3dgs.cli.errors import exit_with_error
from uw3dgs.utils.console import info, route_warnings
from uw3dgs.utils.io import describe_os_error


@dataclass(frozen=True)
class EvalArgs:
    load_config: tyro.conf.Positional[Path]
    """The run's config.yml (outputs/<scene>/<method>/<timestamp>/config.yml)."""
    output_path: Path | None = None
    """Where the metrics JSON goes; default <run>/eval/results.json."""
    render_output_path: Path | None = None
    """Where the test-view renders go (GT, render, depth, side by side); default <run>/eval/renders."""
    save_renders: bool = True
    """Write the renders as PNG."""
    step: int | None = None
    """Evaluate the checkpoint of this step (one the run kept: --steps-per-save, --keep-checkpoints) instead of
    the latest; its metrics and renders then go to <run>/eval/step-<STEP>/ by default."""
    device: str = "auto"


def run_eval(args: EvalArgs) -> dict:
    from uw3dgs.engine.evaluator import evaluate_views, load_trained
    from uw3dgs.engine.trainer import resolve_device
    from uw3dgs.utils.io import unwritable_reason, write_json

    eval_dir = Path(args.load_config).parent / "eval"
    if args.step is not None:  # an earlier checkpoint never overwrites the final evaluation
        eval_dir = eval_dir / f"step-{args.step:06d}"
    renders = (args.render_output_path or eval_dir / "renders") if args.save_renders else None
    output = args.output_path or eval_dir / "results.json"
    # where the results go is checked before the (long) evaluation
    for option, path, folder in (("--output-path", output, False), ("--render-output-path", renders, True)):
        problem = None if path is None else unwritable_reason(path, folder=folder)
        if problem is not None:
            raise ValueError(f"{option} {path}: {problem}")
    device = resolve_device(args.device)
    config, datamanager, model, checkpoint = load_trained(args.load_config, device, step=args.step)
    if not datamanager.test_indices:
        raise ValueError(f"{args.load_config}: the run has no test views (--datamanager.llffhold 0)")
    result = evaluate_views(model, datamanager, progress=True, save_dir=renders)
    summary = {**result["summary"], "num_gaussians": getattr(model, "num_gaussians", None),
               "num_test_views": len(datamanager.test_indices)}
    data = {"experiment_name": config.experiment_name or datamanager.scene_name, "method_name": config.method_name,
            "checkpoint": str(checkpoint), "results": summary, "per_image": result["per_image"]}
    write_json(output, data)
    data["output_path"] = str(output)
    return data


def print_results(data: dict) -> None:
    table = Table(title=f"{data['experiment_name']} / {data['method_name']}")
    table.add_column("metric")
    table.add_column("value", justify="right")
    for key, value in data["results"].items():
        table.add_row(key, f"{value:.4f}" if isinstance(value, float) else "missing" if value is None else str(value))
    Console().print(table)  # the result, on stdout; messages go to the shared console (stderr)
    info(f"metrics written to {data['output_path']}")


def entrypoint(argv: list[str] | None = None) -> None:
    argv = sys.argv[1:] if argv is None else argv
    route_warnings()
    args = tyro.cli(EvalArgs, args=argv, prog="uw-eval", description=__doc__)
    try:
        print_results(run_eval(args))
    except (FileNotFoundError, ValueError, RuntimeError) as exc:
        exit_with_error(exc)
    except OSError as exc:  # e.g. an output folder made read-only during the evaluation
        exit_with_error(exc, message=describe_os_error(exc))
    except KeyboardInterrupt:
        Console().print("Interrupted.")
        sys.exit(130)


if __name__ == "__main__":
    entrypoint()
