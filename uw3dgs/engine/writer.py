"""TensorBoard events of a run (scalars, images and histograms), written into the run folder."""

from __future__ import annotations

from pathlib import Path

import torch
from torch.utils.tensorboard import SummaryWriter


class EventWriter:
    def __init__(self, run_dir: Path):
        self._writer = SummaryWriter(log_dir=str(run_dir))

    def scalars(self, values: dict[str, float], step: int) -> None:
        for name, value in values.items():
            self._writer.add_scalar(name, value, step)

    def image(self, name: str, image: torch.Tensor, step: int) -> None:
        """`image` is [H, W, 3] in [0, 1]."""
        self._writer.add_image(name, image.detach().clamp(0, 1).cpu(), step, dataformats="HWC")

    def histogram(self, name: str, values: torch.Tensor, step: int) -> None:
        self._writer.add_histogram(name, values.detach().float().cpu(), step)

    def close(self) -> None:
        self._writer.close()
