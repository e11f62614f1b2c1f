"""The rich progress bar of training: step, loss, PSNR, Gaussians, steps/s; and RUN/status.json, the same progress
for other processes (`uw-bench`'s grid view): `{"step", "max_steps", "steps_per_second", "time"}`, rewritten
atomically at most every STATUS_SECONDS and when training stops.

It draws on the shared console (`uw3dgs.utils.console.CONSOLE`, stderr), so the `info` / `warn` lines printed
while it runs go above it instead of tearing it. When stderr is not a terminal (a log file, a batch job), a bar
cannot redraw: one plain line is printed every PLAIN_LINE_SECONDS and at the last step instead."""

from __future__ import annotations

import time
from pathlib import Path

from rich.progress import (
    BarColumn,
    MofNCompleteColumn,
    Progress,
    TextColumn,
    TimeElapsedColumn,
    TimeRemainingColumn,
)

from uw3dgs.utils.console import CONSOLE
from uw3dgs.utils.io import write_json

STATUS_FILE = "status.json"
STATUS_SECONDS = 2.0
"""How often status.json is rewritten at most (a write is one small atomic file)."""
PLAIN_LINE_SECONDS = 30.0
"""How often a progress line is printed when stderr is not a terminal."""


class TrainingProgress:
    """Context manager; `update()` once per step. Disabled, it only keeps the speed estimate."""

    def __init__(self, total: int, start: int, enabled: bool = True, smoothing: float = 0.9,
                 status_dir: Path | None = None):
        self.console = CONSOLE
        self.total = total
        self.step = start
        self.status_path = None if status_dir is None else Path(status_dir) / STATUS_FILE
        self._status_written = float("-inf")
        self.enabled = enabled
        self.plain = enabled and not self.console.is_terminal
        """Plain periodic lines instead of the bar (stderr is not a terminal)."""
        self._line_printed = time.monotonic()
        self._start_step = start
        self._started = time.monotonic()
        self.smoothing = smoothing
        self.steps_per_second = 0.0
        self._progress = Progress(
            TextColumn("[bold blue]train"), BarColumn(), MofNCompleteColumn(), TextColumn("{task.fields[stats]}"),
            TimeElapsedColumn(), TimeRemainingColumn(), console=self.console, disable=not enabled or self.plain,
            refresh_per_second=4)
        self._task = self._progress.add_task("train", total=total, completed=start, stats="")

    def __enter__(self) -> TrainingProgress:
        self._progress.__enter__()
        return self

    def __exit__(self, *exc) -> None:
        self._progress.__exit__(*exc)
        self._write_status(force=True)

    def _write_status(self, force: bool = False) -> None:
        now = time.monotonic()
        if self.status_path is None or (not force and now - self._status_written < STATUS_SECONDS):
            return
        self._status_written = now
        write_json(self.status_path, {"step": self.step, "max_steps": self.total,
                                      "steps_per_second": round(self.steps_per_second, 3), "time": time.time()})

    def update(self, step: int, loss: float, metrics: dict[str, float], step_seconds: float) -> None:
        rate = 1.0 / max(step_seconds, 1e-9)
        s = self.smoothing if self.steps_per_second else 0.0
        self.steps_per_second = s * self.steps_per_second + (1 - s) * rate
        self.step = step
        self._write_status()
        parts = [f"loss {loss:.4f}"]
        if "psnr" in metrics:
            parts.append(f"PSNR {metrics['psnr']:.2f}")
        if "num_gaussians" in metrics:
            parts.append(f"{int(metrics['num_gaussians']):,} G")
        parts.append(f"{self.steps_per_second:.1f} it/s")
        self._progress.update(self._task, completed=step, stats=" | ".join(parts))
        if self.plain:
            self._print_line(step, parts)

    def _print_line(self, step: int, parts: list[str]) -> None:
        now = time.monotonic()
        if now - self._line_printed < PLAIN_LINE_SECONDS and step != self.total:
            return
        self._line_printed = now
        done = step - self._start_step
        rate = done / max(now - self._started, 1e-9)
        left = f"{(self.total - step) / rate / 60:.1f} min left" if rate > 0 else "time left unknown"
        line = f"train {step}/{self.total} ({100 * step / max(self.total, 1):.0f}%) | {' | '.join(parts)} | {left}"
        self.console.print(line, soft_wrap=True, highlight=False, markup=False)
