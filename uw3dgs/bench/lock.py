"""A grid's output folder belongs to one `uw-bench` at a time: an exclusive lock on OUTPUT_DIR/.uw-bench.lock, held
from planning the cells to writing the table, naming its holder (pid, host, start). A second `uw-bench` on the
folder refuses in one line instead of classing the first one's live cells as interrupted and training them twice.
The OS drops the lock when the process dies, however it dies."""

from __future__ import annotations

from pathlib import Path

from uw3dgs.engine.run_folder import RunLock

GRID_LOCK_NAME = ".uw-bench.lock"


def _refusal(folder: Path, holder: str) -> str:
    return (f"{folder} is in use by another uw-bench ({holder}); wait for it to end or stop it (it resumes where it "
            "stopped), or give this grid another folder with --output-dir")


def grid_lock(output_dir: Path) -> RunLock:
    """The (not yet acquired) lock of a grid's output folder; `acquire()` raises RunFolderError naming the holder."""
    return RunLock(output_dir, GRID_LOCK_NAME, _refusal)
