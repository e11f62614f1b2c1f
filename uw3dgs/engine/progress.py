"""The rich progress bar of training: step, loss, PSNR, Gaussians, steps/s.

It draws on the shared console (`uw3dgs.utils.console.CONSOLE`, stderr), so the `info` / `warn` lines printed
while it runs go above it instead of tearing it."""

from __future__ import annotations

from rich.progress import (
    BarColumn,
    MofNCompleteColumn,
    Progress,
    TextColumn,
    TimeElapsedColumn,
    TimeRemainingColumn,
)

from uw3dgs.utils.console import CONSOLE


class TrainingProgress:
    """Context manager; `update()` once per step. Disabled, it only keeps the speed estimate."""

    def __init__(self, total: int, start: int, enabled: bool = True, smoothing: float = 0.9):
        self.console = CONSOLE
        self.enabled = enabled
        self.smoothing = smoothing
        self.steps_per_second = 0.0
        self._progress = Progress(
            TextColumn("[bold blue]train"), BarColumn(), MofNCompleteColumn(), TextColumn("{task.fields[stats]}"),
            TimeElapsedColumn(), TimeRemainingColumn(), console=self.console, disable=not enabled,
            refresh_per_second=4)
        self._task = self._progress.add_task("train", total=total, completed=start, stats="")

    def __enter__(self) -> TrainingProgress:
        self._progress.__enter__()
        return self

    def __exit__(self, *exc) -> None:
        self._progress.__exit__(*exc)

    def update(self, step: int, loss: float, metrics: dict[str, float], step_seconds: float) -> None:
        rate = 1.0 / max(step_seconds, 1e-9)
        s = self.smoothing if self.steps_per_second else 0.0
        self.steps_per_second = s * self.steps_per_second + (1 - s) * rate
        parts = [f"loss {loss:.4f}"]
        if "psnr" in metrics:
            parts.append(f"PSNR {metrics['psnr']:.2f}")
        if "num_gaussians" in metrics:
            parts.append(f"{int(metrics['num_gaussians']):,} G")
        parts.append(f"{self.steps_per_second:.1f} it/s")
        self._progress.update(self._task, completed=step, stats=" | ".join(parts))
