"""`uw-eval CONFIG.yml`: render the test views of a trained run and write its metrics as JSON.
`uw-eval table RUN_OR_DIR...`: a table over runs, mean +- std per scene and method (see `uw-eval table --help`)."""

from __future__ import annotations

import json
import sys
from dataclasses import dataclass
from pathlib import Path
from typing import Literal

import tyro
from rich.console import Console
from rich.table import Table

from uw3dgs.cli.errors import exit_with_error
from uw3dgs.utils.console import info, route_warnings, warn
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


def recorded_train_time(run_dir: Path, checkpoint: Path) -> tuple[float | None, int | None]:
    """(train_seconds, train_steps) of a checkpoint: the seconds uw-train recorded up to its step (RUN/train_time.json;
    where that file is unreadable or lacks the step, the checkpoint itself), None where the run predates the record;
    the step from the checkpoint's name."""
    from uw3dgs.engine.checkpoint import load_checkpoint
    from uw3dgs.engine.trainer import read_train_time

    name = checkpoint.name.removeprefix("step-").removesuffix(".ckpt")
    step = int(name) if name.isdigit() else None
    record = read_train_time(run_dir)
    if step is None:
        return None, step
    seconds = None if record is None else record["checkpoints"].get(str(step))
    if isinstance(seconds, bool) or not isinstance(seconds, (int, float)):
        # killed between the checkpoint and the record, or the record damaged: the checkpoint holds it (a run from
        # before the record has it in neither: nothing made up)
        seconds = load_checkpoint(checkpoint, "cpu").get("train_seconds")
    return (float(seconds) if isinstance(seconds, (int, float)) else None), step


def run_notes(run_dir: Path) -> dict[str, object]:
    """The run's notes on how it started (RUN/notes/NAME.json -> NAME: content; `Model.run_notes`), e.g. the
    medium's identifiability report; {} for a run without any."""
    from uw3dgs.engine.run_folder import NOTES_DIR

    return {path.stem: json.loads(path.read_text()) for path in sorted((run_dir / NOTES_DIR).glob("*.json"))}


def run_eval(args: EvalArgs, progress: bool = True) -> dict:
    from uw3dgs.engine.evaluator import evaluate_views, load_trained
    from uw3dgs.engine.run_identity import DATA_KEY, data_record
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
    result = evaluate_views(model, datamanager, progress=progress, save_dir=renders)
    train_seconds, train_steps = recorded_train_time(Path(args.load_config).parent, Path(checkpoint))
    summary = {**result["summary"], "num_gaussians": getattr(model, "num_gaussians", None),
               "num_test_views": len(datamanager.test_indices), "train_seconds": train_seconds,
               "train_steps": train_steps}
    notes = run_notes(Path(args.load_config).parent)
    data = {"experiment_name": config.experiment_name or datamanager.scene_name, "method_name": config.method_name,
            "checkpoint": str(checkpoint), "results": summary, DATA_KEY: data_record(config, datamanager),
            "per_image": result["per_image"], "notes": notes}
    data.update(model.eval_report(notes))
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
    if argv and argv[0] == "table":  # the subcommand; a run is named by its config.yml (./table/config.yml)
        table_entrypoint(argv[1:])
        return
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


# ---- uw-eval table ---------------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class TableArgs:
    runs: tyro.conf.Positional[tuple[Path, ...]]
    """Run folders, their config.yml, or folders holding runs (searched recursively for config.yml)."""
    format: Literal["md", "tex", "csv", "json"] = "md"
    """md: a GitHub table, tex: a booktabs tabular (methods in rows, scenes as column groups); csv, json: one row per
    scene x method with <metric>_mean, _std, _n."""
    output: Path | None = None
    """Write the table to this file instead of printing it."""
    metrics: str | None = None
    """The columns, result keys separated by commas (e.g. psnr,ssim,lpips_vgg,depth_abs_rel); default psnr, ssim,
    lpips_alex, uri_psnr, floater_ratio, num_gaussians, train_minutes, those no run has dropped."""
    eval: bool = True
    """Evaluate (as uw-eval RUN/config.yml does, renders included) the runs without eval/results.json and those
    trained on since; --no-eval lists the former as skipped and shows the latter as they are."""
    device: str = "auto"
    """Where the runs without results are evaluated."""


def run_table(args: TableArgs) -> str:
    """Find the runs, evaluate those without results (unless --no-eval), and render the table."""
    from uw3dgs.engine import results_table as rt
    from uw3dgs.engine.run_folder import lock_holder
    from uw3dgs.utils.io import unwritable_reason

    if not args.runs:
        raise ValueError("uw-eval table: give the runs: run folders, their config.yml, or folders holding runs")
    requested = rt.parse_metrics(args.metrics)
    run_dirs, empty = rt.find_runs(args.runs)
    if not run_dirs:
        raise FileNotFoundError(f"no runs (folders holding a config.yml) found under {', '.join(map(str, args.runs))}")
    for path in empty:
        warn(f"no runs (folders holding a config.yml) under {path}")
    problem = None if args.output is None else unwritable_reason(args.output)
    if problem is not None:  # before any evaluation
        raise ValueError(f"--output {args.output}: {problem}")
    runs, skipped, to_evaluate = [], [], []
    for run_dir in run_dirs:
        holder = lock_holder(run_dir)
        if holder is not None:  # its checkpoints are mid-run: evaluating one would file a number for an unfinished run
            skipped.append(f"{run_dir}: still training ({holder}); run uw-eval table again when it has ended")
            continue
        try:
            data = rt.read_results(run_dir)
        except ValueError as exc:
            skipped.append(f"{run_dir}: {exc}")
            continue
        stale = None if data is None else rt.stale_results(run_dir, data)
        if data is None or (stale is not None and args.eval):
            if args.eval:
                to_evaluate.append((run_dir, stale or f"no {rt.RESULTS}"))
            else:
                skipped.append(f"{run_dir}: no {rt.RESULTS} (--no-eval); evaluate it with uw-eval "
                               f"{run_dir / 'config.yml'}")
            continue
        if stale is not None:
            warn(f"{stale}: shown as it is (--no-eval)")
        runs.append(rt.run_from_results(run_dir, data))
    for i, (run_dir, why) in enumerate(to_evaluate, 1):
        info(f"evaluating {run_dir} ({i}/{len(to_evaluate)}; {why})")
        try:
            data = run_eval(EvalArgs(load_config=run_dir / "config.yml", device=args.device), progress=False)
        except (FileNotFoundError, ValueError, RuntimeError) as exc:
            skipped.append(f"{run_dir}: cannot be evaluated ({exc})")
            continue
        runs.append(rt.run_from_results(run_dir, data))
    for message in skipped:
        warn(f"skipped {message}")
    if not runs:
        raise ValueError(f"none of the {len(run_dirs)} run(s) found has results to show (skipped: see above)")
    metrics, dropped = rt.select_metrics(runs, requested)
    if dropped:
        warn(f"--metrics: no run has {', '.join(dropped)}; column(s) dropped")
    if not metrics:
        raise ValueError(f"none of the metrics asked for is in these runs; they have: "
                         f"{', '.join(rt.available_metrics(runs))}")
    table = rt.build_table(runs, metrics)
    for note in table.notes:
        warn(note)
    return rt.render(table, args.format)


def table_entrypoint(argv: list[str]) -> None:
    """`uw-eval table ...`: the table to stdout, or to --output (then its path on stderr)."""
    from uw3dgs.utils.io import write_text

    args = tyro.cli(TableArgs, args=argv, prog="uw-eval table",
                    description="A table of runs' metrics: mean +- std over the runs (seeds) of every scene and "
                                "method, the best of each column in bold (docs/grids.md, 'Tables over runs').")
    try:
        text = run_table(args)
        if args.output is None:
            sys.stdout.write(text)
        else:
            write_text(args.output, text)
            info(f"table written to {args.output}")
    except (FileNotFoundError, ValueError, RuntimeError) as exc:
        exit_with_error(exc)
    except OSError as exc:
        exit_with_error(exc, message=describe_os_error(exc))
    except KeyboardInterrupt:
        Console().print("Interrupted.")
        sys.exit(130)


if __name__ == "__main__":
    entrypoint()
