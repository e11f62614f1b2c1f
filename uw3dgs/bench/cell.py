"""One cell of a grid: what its run folder holds (new, interrupted, trained, evaluated), and running what is left as
child processes (`uw-train`, then `uw-eval`), so that a cell killed with its process leaves a normal run folder that
the next `uw-bench` resumes from its checkpoint.

`run_cell` is what every executor calls (a thread of the local executor, a Ray task on a cluster node); it returns a
plain `Outcome`, so the driver needs nothing from the worker but that.
"""

from __future__ import annotations

import dataclasses
import json
import os
import signal
import subprocess
import sys
import threading
import time
from dataclasses import dataclass
from enum import Enum
from pathlib import Path
from typing import Any

from uw3dgs.bench.grid import Cell
from uw3dgs.config import REMOVED_OPTIONS
from uw3dgs.engine.checkpoint import checkpoint_step, latest_checkpoint
from uw3dgs.engine.results_table import RESULTS, read_results, stale_results
from uw3dgs.engine.run_folder import RunFolderError, RunLock, flatten, holds_a_run, lock_holder
from uw3dgs.utils.io import describe_os_error
from uw3dgs.utils.safe_yaml import load_yaml

LOG_NAME = "bench.log"
"""The cell's uw-train and uw-eval output, appended run after run, in its run folder."""
IGNORED_OPTIONS = {"timestamp", "load_config", "resume", "progress", "device", "viewer", "viewer_port", "viewer_host",
                   "output_dir"}
"""Options that may differ between the grid's command line and the run folder's config.yml of the same cell; the
output_dir is where the folder was first written: a grid folder moved or copied elsewhere resumes where it is now."""
KEEP_ADVICE = ("move that folder aside (uw-bench never deletes a run) to run the cell with the grid's settings, or "
               "give the grid another output_dir")


class State(str, Enum):
    NEW = "new"
    """No run in the folder: train from step 0."""
    RESUME = "resume"
    """A run that stopped before its last step: continue it from its latest checkpoint."""
    RESTART = "restart"
    """A run that stopped before its first checkpoint: nothing to keep; its folder is moved aside, trained anew."""
    EVALUATE = "evaluate"
    """Trained to its last step, not evaluated (or evaluated before it was trained on)."""
    DONE = "done"
    """Trained and evaluated: skipped."""
    CONFLICT = "conflict"
    """The folder holds a run of other settings: not touched."""


@dataclass(frozen=True)
class Outcome:
    cell: Cell
    status: str
    """'done' (results available), 'failed', 'interrupted' (resumable), 'conflict' or 'not selected' (left out by
    uw-bench's --methods/--datasets/--variants/--seeds)."""
    message: str = ""
    results: dict[str, Any] | None = None
    """uw-eval's JSON of the run."""


def expected_config(cell: Cell) -> dict[str, Any]:
    """The config the cell's command line builds, as config.yml would hold it (datamanager resolved)."""
    from uw3dgs.cli.train import parse_config
    from uw3dgs.config import config_to_dict
    from uw3dgs.data.datamanager import AutoDataManagerConfig

    config = parse_config(list(cell.argv))
    if isinstance(config.datamanager, AutoDataManagerConfig):
        config = dataclasses.replace(config, datamanager=config.datamanager.resolve(config.data))
    return config_to_dict(config)


def as_loaded(saved: dict[str, Any]) -> dict[str, Any]:
    """A run's saved config as `uw-train --load-config` reads it: options added since the run was written take
    their defaults (which keep the behaviour the run had), options removed since are dropped. A config that does not
    load is compared as written (the differences then name what is wrong)."""
    from uw3dgs.config import config_from_dict, config_to_dict

    try:
        return config_to_dict(config_from_dict(saved))
    except (ValueError, TypeError, ImportError):
        return saved


def config_differences(saved: dict[str, Any], expected: dict[str, Any]) -> list[str]:
    """The options whose values differ, as 'key (saved in the run, in the grid)'; paths compared resolved, options
    removed since the run was saved (`uw3dgs.config.REMOVED_OPTIONS`) skipped."""
    a, b = flatten(saved), flatten(expected)
    out = []
    for key in dict.fromkeys([*a, *b]):
        if key.split(".")[0] in IGNORED_OPTIONS:
            continue
        x, y = a.get(key, "<absent>"), b.get(key, "<absent>")
        if key.rpartition(".")[2] in REMOVED_OPTIONS and y == "<absent>":  # said again by a `_type` both have
            continue
        if key in ("data", "output_dir") and isinstance(x, str) and isinstance(y, str):
            x, y = str(Path(x).resolve()), str(Path(y).resolve())
        if x != y:
            out.append(f"{key} ({a.get(key, '<absent>')!r} in the run, {b.get(key, '<absent>')!r} in the grid)")
    return out


def cell_state(cell: Cell, check_config: bool = True) -> tuple[State, str]:
    """What is left to do for the cell, and why; `check_config`: compare the folder's config.yml with the cell's
    options (a conflict where they differ)."""
    run = cell.run_dir
    holder = lock_holder(run)
    if holder is not None:
        return State.CONFLICT, (f"{run} is in use by another training ({holder}); let it end, or stop it and run "
                                "uw-bench again")
    if not holds_a_run(run):
        return State.NEW, "not started"
    config_file = run / "config.yml"
    if not config_file.is_file():
        return State.CONFLICT, f"{run} holds checkpoints but no config.yml (not a run uw-train wrote); {KEEP_ADVICE}"
    try:
        saved = load_yaml(config_file) or {}
    except (OSError, ValueError) as exc:
        return State.CONFLICT, f"{exc if isinstance(exc, ValueError) else describe_os_error(exc)}; {KEEP_ADVICE}"
    if not isinstance(saved, dict):
        return State.CONFLICT, f"{config_file} is not a uw3dgs config (not a mapping); {KEEP_ADVICE}"
    if check_config:
        differences = config_differences(as_loaded(saved), expected_config(cell))
        if differences:
            shown = "; ".join(differences[:4]) + (f"; ... ({len(differences)} in all)" if len(differences) > 4 else "")
            return State.CONFLICT, f"{run} holds a run made with other settings: {shown}; {KEEP_ADVICE}"
    checkpoint = latest_checkpoint(run)
    if checkpoint is None:
        return State.RESTART, "stopped before its first checkpoint"
    step = checkpoint_step(checkpoint)
    last = int(flatten(saved).get("max_num_iterations", step))
    if step < last:
        return State.RESUME, f"at step {step} of {last}"
    if not (run / RESULTS).is_file():
        return State.EVALUATE, "trained, not evaluated"
    try:
        stale = stale_results(run, read_results(run))
    except ValueError as exc:  # unreadable results: uw-eval writes them anew
        return State.EVALUATE, str(exc)
    return (State.EVALUATE, stale) if stale else (State.DONE, "trained and evaluated")


def child_env(threads: int) -> dict[str, str]:
    """The environment of a cell's processes: this one's, with the thread count of a job (OpenMP and MKL, which
    torch and the compiled CPU backend read at start)."""
    return {**os.environ, "OMP_NUM_THREADS": str(threads), "MKL_NUM_THREADS": str(threads)}


STOP_SECONDS = 120.0
"""How long a stopped child may take to finish its step and write its checkpoint before it is killed."""
_children: set[subprocess.Popen] = set()
_children_lock = threading.Lock()


def stop_children() -> None:
    """Ask every running child process of this process's cells to stop (SIGTERM: uw-train finishes its step and
    writes its checkpoint); the cells' threads then see them exit."""
    with _children_lock:
        for proc in _children:
            if proc.poll() is None:
                proc.send_signal(signal.SIGTERM)


def _run(command: list[str], log: Path, env: dict[str, str]) -> int:
    """Run `command` with its output appended to `log`; if this thread is interrupted (a Ray task cancelled), the
    child is stopped as `stop_children` does and waited for."""
    log.parent.mkdir(parents=True, exist_ok=True)
    with open(log, "a") as out:
        out.write(f"\n$ {' '.join(command)}   # {time.strftime('%Y-%m-%d %H:%M:%S')}\n")
        out.flush()
        proc = subprocess.Popen(command, stdout=out, stderr=subprocess.STDOUT, env=env, stdin=subprocess.DEVNULL)
        with _children_lock:
            _children.add(proc)
        try:
            return proc.wait()
        except BaseException:
            proc.send_signal(signal.SIGTERM)
            try:
                proc.wait(STOP_SECONDS)
            except subprocess.TimeoutExpired:
                proc.kill()
            raise
        finally:
            with _children_lock:
                _children.discard(proc)


def _log_tail(log: Path, lines: int = 3) -> str:
    try:
        tail = [line for line in log.read_text(errors="replace").splitlines() if line.strip()][-lines:]
    except OSError:
        return ""
    return " | ".join(line.strip() for line in tail)


def _move_aside(run: Path) -> Path:
    """A folder with a config.yml and no checkpoint holds nothing to resume; it is kept, hidden (`uw-eval table`
    does not search folders starting with a dot), under a new name. Moved with its run lock held by this process,
    so a training that holds it (started meanwhile) is never moved: RunFolderError naming it."""
    target = run.with_name(f".{run.name}.restarted-{time.strftime('%Y%m%d-%H%M%S')}")
    lock = RunLock(run)
    lock.acquire()
    try:
        run.rename(target)
    finally:
        lock.release()
    return target


def run_cell(cell: Cell, threads: int, python: str = sys.executable) -> Outcome:
    """Train what is left of the cell and evaluate it, as child processes with `threads` threads each. The driver
    planned the cell (`cell_state` with its options checked against the folder), so they are not parsed again."""
    state, why = cell_state(cell, check_config=False)
    if state is State.CONFLICT:
        return Outcome(cell, "conflict", why)
    if state is State.DONE:
        return Outcome(cell, "done", why, read_results(cell.run_dir))
    started = time.monotonic()
    log = cell.run_dir / LOG_NAME
    env = child_env(threads)
    done = {State.NEW: "trained and evaluated", State.RESUME: f"resumed {why}, trained and evaluated",
            State.EVALUATE: f"evaluated ({why})"}.get(state)
    if state is State.RESTART:
        try:
            done = f"{why}, trained again and evaluated (the old folder is {_move_aside(cell.run_dir)})"
        except RunFolderError as exc:
            return Outcome(cell, "conflict", str(exc))
    if state in (State.NEW, State.RESTART, State.RESUME):
        command = [python, "-m", "uw3dgs.cli.train", *cell.argv]
        if state is State.RESUME:
            command = [python, "-m", "uw3dgs.cli.train", "--load-config", str(cell.run_dir / "config.yml"), "--resume",
                       "--no-progress"]
        code = _run(command, log, env)
        if code in (130, 143):  # stopped by Ctrl-C or SIGTERM after writing a checkpoint
            return Outcome(cell, "interrupted", f"stopped ({_log_tail(log, 1)}); run uw-bench again to resume it")
        if code != 0:
            return Outcome(cell, "failed", f"uw-train exited with status {code}: {_log_tail(log)} (log: {log})")
    code = _run([python, "-m", "uw3dgs.cli.eval", str(cell.run_dir / "config.yml")], log, env)
    if code != 0:
        return Outcome(cell, "failed", f"uw-eval exited with status {code}: {_log_tail(log)} (log: {log})")
    return Outcome(cell, "done", f"{done} in {time.monotonic() - started:.0f} s", read_results(cell.run_dir))


def read_status(cell: Cell) -> dict[str, Any] | None:
    """The cell's training progress as uw-train writes it (RUN/status.json), or None."""
    from uw3dgs.engine.progress import STATUS_FILE

    try:
        data = json.loads((cell.run_dir / STATUS_FILE).read_text())
    except (OSError, ValueError):
        return None
    return data if isinstance(data, dict) else None
