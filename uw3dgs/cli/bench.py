"""`uw-bench GRID.yaml`: run an experiment grid (methods x datasets x seeds x variants; `uw3dgs/bench/grid.py` has
the file's layout), resumably, on this machine or a Ray cluster, and write its table (docs/grids.md,
"Experiment grids")."""

from __future__ import annotations

import dataclasses
import signal
import sys
from dataclasses import dataclass
from pathlib import Path
from typing import Literal

import tyro
from rich.console import Console

from uw3dgs.cli.errors import exit_with_error
from uw3dgs.utils.console import info, route_warnings, warn
from uw3dgs.utils.io import describe_os_error

TABLE_FORMATS = ("md", "tex", "csv")
"""The table files written to OUTPUT_DIR/table.<format>; the Markdown one is also printed."""


@dataclass(frozen=True)
class BenchArgs:
    grid: tyro.conf.Positional[Path]
    """The grid file (configs/demo.yaml, configs/paper-table1.yaml, or your own)."""
    jobs: int = 1
    """Cells run at once by the local executor; the cores are divided among them (never oversubscribed)."""
    threads_per_job: int | None = None
    """Threads of each cell (OpenMP); default: the cores divided by --jobs (local), 1 (ray)."""
    executor: Literal["local", "ray"] = "local"
    """local: this machine; ray: one Ray task per cell on a Ray cluster (pip install ray)."""
    ray_address: str | None = None
    """The Ray cluster ('auto', 'ray://head:10001'); default Ray's own (RAY_ADDRESS, else a new local instance);
    'local' starts a local instance with this machine's cores."""
    gpus_per_job: float = 0.0
    """GPUs each Ray task asks for (with --executor ray; add --device cuda to the grid's args)."""
    data_root: Path | None = None
    """Replaces the grid's data_root: where its datasets' folders are."""
    output_dir: Path | None = None
    """Replaces the grid's output_dir: where the cells' run folders and the table go."""
    dry_run: bool = False
    """List every cell, what is left to do for it and its uw-train command; run nothing."""
    table: bool = True
    """Write the table at the end (--no-table: only run the cells)."""
    methods: tuple[str, ...] = ()
    """Run only the cells of these methods (default: all); the table still shows every finished cell."""
    datasets: tuple[str, ...] = ()
    """Run only the cells of these datasets (the grid's names for them; default: all)."""
    variants: tuple[str, ...] = ()
    """Run only the cells of these variants (the grid's `variants:` names; default: all)."""
    seeds: tuple[int, ...] = ()
    """Run only the cells of these seeds (default: all)."""


def plan(args: BenchArgs, grid):
    """The grid's cells and each cell's state. Every cell's options are checked here (uw-train's own parser, once
    per dataset x method x variant: the seed changes nothing else), so a typo stops the grid before any run starts,
    not hours into it."""
    from uw3dgs.bench.cell import cell_state, expected_config
    from uw3dgs.bench.grid import GridError

    cells = grid.cells()
    checked = set()
    states = []
    for cell in cells:
        try:
            if (cell.dataset, cell.label) not in checked:
                expected_config(cell)
                checked.add((cell.dataset, cell.label))
            states.append(cell_state(cell))
        except SystemExit as exc:  # tyro's verdict on a bad flag (it printed why)
            raise GridError(f"{args.grid}: cell {cell.name}: uw-train refuses its options (above): "
                            f"uw-train {' '.join(cell.argv)}") from exc
        except (ValueError, FileNotFoundError) as exc:
            raise GridError(f"{args.grid}: cell {cell.name}: {exc}") from exc
    return cells, states


def write_table(grid, outcomes, print_to=sys.stdout) -> None:
    """The table of the done cells (rows: method [variant], column groups: datasets) to OUTPUT_DIR/table.*; the
    cells without results are listed under it."""
    from uw3dgs.engine import results_table as rt
    from uw3dgs.utils.io import write_text

    runs = [dataclasses.replace(rt.run_from_results(o.cell.run_dir, o.results), scene=o.cell.dataset,
                                method=o.cell.label)
            for o in outcomes if o.status == "done" and o.results is not None]
    missing = [f"{o.cell.name}: {o.status}: {o.message}" for o in outcomes if o.status != "done" or o.results is None]
    if not runs:
        warn("no cell has results: no table written")
        return
    metrics, dropped = rt.select_metrics(runs, grid.metrics)
    if dropped:
        warn(f"metrics: no run has {', '.join(dropped)}; column(s) dropped")
    table = rt.build_table(runs, metrics)
    for note in table.notes:
        warn(note)
    texts = {fmt: rt.render(table, fmt) for fmt in TABLE_FORMATS}
    if missing:
        texts["md"] += "\nNot in the table:\n\n" + "".join(f"- {line}\n" for line in missing)
        texts["tex"] += "".join(f"% not in the table: {line}\n" for line in missing)
    for fmt, text in texts.items():
        write_text(grid.output_dir / f"table.{fmt}", text)
    print_to.write(texts["md"])
    info(f"table written to {', '.join(str(grid.output_dir / f'table.{fmt}') for fmt in TABLE_FORMATS)}")


def run_bench(args: BenchArgs) -> int:
    """Run the grid; the exit status: 0 when every selected cell is done, 1 otherwise (the table shows what is
    done). The grid's output folder is locked for the whole run (a --dry-run only reads it)."""
    from uw3dgs.bench.grid import load_grid
    from uw3dgs.bench.lock import grid_lock

    grid = load_grid(args.grid, args.data_root, args.output_dir)
    if args.dry_run:
        return _run_locked(args, grid)
    lock = grid_lock(grid.output_dir)
    lock.acquire()
    try:
        return _run_locked(args, grid)
    finally:
        lock.release()


def _run_locked(args: BenchArgs, grid) -> int:
    from uw3dgs.bench.cell import Outcome, State
    from uw3dgs.bench.executors import available_cores, local_threads, run_local, run_ray
    from uw3dgs.bench.grid import select_cells
    from uw3dgs.bench.view import GridView
    from uw3dgs.engine.results_table import read_results

    cells, states = plan(args, grid)
    selected = {cell.name for cell in select_cells(grid, args.methods, args.datasets, args.variants, args.seeds)}
    counts = {s: sum(1 for state, _ in states if state is s) for s in State}
    info(f"{args.grid}: {len(cells)} cells in {grid.output_dir}: "
         + ", ".join(f"{n} {s.value}" for s, n in counts.items() if n))
    if len(selected) < len(cells):
        info(f"{len(selected)} of them selected (--methods/--datasets/--variants/--seeds); the others are not run")
    if args.dry_run:
        for cell, (state, why) in zip(cells, states, strict=True):
            chosen = "" if cell.name in selected else ", not selected"
            print(f"{cell.name}: {state.value} ({why}{chosen})\n    uw-train {' '.join(cell.argv)}", flush=True)
        return 0
    outcomes = [Outcome(cell, "done", why, read_results(cell.run_dir))
                for cell, (state, why) in zip(cells, states, strict=True) if state is State.DONE]
    outcomes += [Outcome(cell, "conflict", why) for cell, (state, why) in zip(cells, states, strict=True)
                 if state is State.CONFLICT]
    for outcome in outcomes:
        if outcome.status == "conflict":
            warn(f"{outcome.cell.name}: {outcome.message}")
    left = [cell for cell, (state, _) in zip(cells, states, strict=True) if state not in (State.DONE, State.CONFLICT)]
    todo = [cell for cell in left if cell.name in selected]
    outcomes += [Outcome(cell, "not selected", "not chosen by --methods/--datasets/--variants/--seeds")
                 for cell in left if cell.name not in selected]
    if todo:
        # SIGTERM (a scheduler, kill) stops the grid like Ctrl-C: the running cells checkpoint, the next run resumes.
        # Installed here, after the imports: pycolmap's glog installs its own SIGTERM handler when first imported.
        signal.signal(signal.SIGTERM, _sigterm_as_interrupt)
        if args.executor == "local":
            threads = local_threads(args.jobs, args.threads_per_job, available_cores())
            info(f"running {len(todo)} cell(s), {args.jobs} at a time, {threads} thread(s) each")
        else:
            threads = args.threads_per_job or 1
            info(f"sending {len(todo)} cell(s) to Ray, {threads} CPU(s) and {args.gpus_per_job} GPU(s) each")
        with GridView(todo) as view:
            if args.executor == "local":
                outcomes += run_local(todo, args.jobs, threads, view.done, view.refresh)
            else:
                outcomes += run_ray(todo, args.ray_address, threads, args.gpus_per_job, view.done, view.refresh)
    order = {cell.name: i for i, cell in enumerate(cells)}
    outcomes.sort(key=lambda o: order[o.cell.name])
    if args.table:
        write_table(grid, outcomes)
    return 0 if all(o.status in ("done", "not selected") for o in outcomes) else 1


def _sigterm_as_interrupt(signum: int, frame: object) -> None:
    raise KeyboardInterrupt


def entrypoint(argv: list[str] | None = None) -> None:
    argv = sys.argv[1:] if argv is None else argv
    route_warnings()
    args = tyro.cli(BenchArgs, args=argv, prog="uw-bench",
                    description="Run an experiment grid (methods x datasets x seeds x variants) and write its table.")
    try:
        sys.exit(run_bench(args))
    except KeyboardInterrupt:
        Console(stderr=True).print("Interrupted: the running cells wrote their checkpoints; run the same uw-bench "
                                   "command again to resume them.", soft_wrap=True)
        sys.exit(130)
    except (FileNotFoundError, ValueError, RuntimeError) as exc:
        exit_with_error(exc)
    except OSError as exc:
        exit_with_error(exc, message=describe_os_error(exc))


if __name__ == "__main__":
    entrypoint()
