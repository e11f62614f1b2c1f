"""The progress view of a grid: a bar over its cells and one line per running cell (step, steps/s, from the
RUN/status.json uw-train writes), redrawn in place on a terminal; elsewhere (a log file, CI) one line per finished
cell."""

from __future__ import annotations

import time
from collections.abc import Sequence

from rich.console import Group
from rich.live import Live
from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn
from rich.table import Table

from uw3dgs.bench.cell import Outcome, read_status
from uw3dgs.bench.grid import Cell
from uw3dgs.utils.console import CONSOLE, info, warn

FRESH_SECONDS = 60.0
"""A cell whose status.json is older than this is not shown as running (uw-train rewrites it every few seconds)."""


class GridView:
    """Context manager; `done(outcome)` for every finished cell, `refresh()` as often as the driver polls."""

    def __init__(self, cells: Sequence[Cell]):
        self.cells = list(cells)
        self.finished: set[str] = set()
        self._bar = Progress(TextColumn("[bold blue]grid"), BarColumn(), MofNCompleteColumn(),
                             TextColumn("cells"), TimeElapsedColumn(), console=CONSOLE)
        self._task = self._bar.add_task("grid", total=len(cells))
        self._live = Live(self._render(), console=CONSOLE, refresh_per_second=1, transient=False)

    def __enter__(self) -> GridView:
        self._live.__enter__()
        return self

    def __exit__(self, *exc: object) -> None:
        self._live.update(self._render())
        self._live.__exit__(*exc)
        if not CONSOLE.is_terminal:  # rich leaves its last drawing without a line end when not on a terminal
            CONSOLE.line()

    def _render(self) -> Group:
        table = Table(box=None, show_header=True, header_style="bold", pad_edge=False)
        for column in ("running cell", "step", "it/s"):
            table.add_column(column, justify="left" if column == "running cell" else "right")
        for cell in self.cells:
            if cell.name in self.finished:
                continue
            status = read_status(cell)
            if status is None or time.time() - float(status.get("time", 0)) > FRESH_SECONDS:
                continue  # not started, or a status left by an earlier invocation
            step, last = status.get("step"), status.get("max_steps")
            trained = step is not None and step == last
            table.add_row(cell.name, "evaluating" if trained else f"{step}/{last}",
                          "" if trained else f"{status.get('steps_per_second', 0):.1f}")
        return Group(self._bar, table) if table.row_count else Group(self._bar)

    def refresh(self) -> None:
        self._live.update(self._render())

    def done(self, outcome: Outcome) -> None:
        self.finished.add(outcome.cell.name)
        self._bar.advance(self._task)
        if outcome.status == "done":
            info(f"{outcome.cell.name}: done ({outcome.message})")
        else:
            warn(f"{outcome.cell.name}: {outcome.status}: {outcome.message}")
        self.refresh()
