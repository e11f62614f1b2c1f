"""A first run sized to the images and to the machine: the downscale factor and step count `uw-process-data`
suggests, with the time it expects.

Time per step is modelled as base + per_megapixel x (pixels per image / 10^6): the base is what does not grow with
the image (the Gaussians' projection, sorting, optimiser steps), the other term the per-pixel compositing. The two
constants are `StepCost`'s defaults, measured for `uw3dgs` on the CPU backend on a real scene seeded with SfM
points (docs/run-time.md has the measurement, its command and how the estimate compares
with whole runs); the Gaussians' count moves the base, so it is a guide, not a promise. No GPU cost was measured: on
a GPU the suggestion is 3DGS's own setting (longest side at most 1600 px, 30,000 steps) without a time.
"""

from __future__ import annotations

from dataclasses import dataclass

from uw3dgs.options import CheckedConfig, check_number


@dataclass(frozen=True)
class StepCost(CheckedConfig):
    """Seconds per `uw3dgs` training step on the CPU: base_s + per_megapixel_s x megapixels per image."""

    base_s: float = 0.11
    """Seconds per step that do not grow with the image size (docs/run-time.md)."""
    per_megapixel_s: float = 1.05
    """Seconds per step per million pixels of the training image (the same measurement)."""

    def check_options(self) -> None:
        super().check_options()
        check_number(self, "base_s", ge=0)
        check_number(self, "per_megapixel_s", ge=0)

    def seconds_per_step(self, width: int, height: int) -> float:
        return self.base_s + self.per_megapixel_s * width * height / 1e6


@dataclass(frozen=True)
class RunSize:
    factor: int
    """--downscale-factor."""
    steps: int
    """--max-num-iterations."""
    seconds: float | None
    """Expected training time (None: not measured for this machine kind)."""
    width: int
    height: int
    """Training image size at that factor."""


GPU_MAX_SIDE = 1600
"""3DGS's own rule: images with a longer side than this are downscaled to it."""
GPU_STEPS = 30000
MIN_SIDE = 64
"""The smallest longest side suggested: below it a scene's detail is gone."""
STEP_QUANTUM = 500


def size_run(width: int, height: int, device: str, budget_s: float, cpu_steps: int,
             cost: StepCost = StepCost()) -> RunSize:
    """The suggestion for images of `width` x `height` on `device` ('cpu' or 'cuda').

    CPU: `cpu_steps` steps at the smallest power-of-two factor whose expected time fits `budget_s`; when even the
    coarsest factor (longest side >= MIN_SIDE) does not fit, fewer steps (multiples of STEP_QUANTUM, at least one
    quantum). GPU: the factor that brings the longest side to GPU_MAX_SIDE or below, GPU_STEPS, no time."""
    def size(factor: int) -> tuple[int, int]:
        return width // factor, height // factor

    if device == "cuda":
        factor = 1
        while max(size(factor)) > GPU_MAX_SIDE:
            factor *= 2
        return RunSize(factor, GPU_STEPS, None, *size(factor))
    factor = 1
    while True:
        per_step = cost.seconds_per_step(*size(factor))
        coarser = max(size(factor * 2)) >= MIN_SIDE
        if per_step * cpu_steps <= budget_s or not coarser:
            break
        factor *= 2
    steps = cpu_steps
    if per_step * steps > budget_s:
        steps = max(STEP_QUANTUM, int(budget_s / per_step) // STEP_QUANTUM * STEP_QUANTUM)
    return RunSize(factor, steps, per_step * steps, *size(factor))


def suggestion(method: str, data: str, size: RunSize, device: str) -> str:
    """The command line and what it expects, for the end of uw-process-data."""
    command = (f"uw-train {method} --data {data} --downscale-factor {size.factor} "
               f"--max-num-iterations {size.steps}")
    where = f"{size.width}x{size.height} px"
    if size.seconds is None:
        return f"Train on it with: {command}\n  ({where} on the GPU; no time estimate: no GPU cost was measured)"
    return (f"Train on it with: {command}\n  ({where} on this CPU: about {size.seconds / 60:.0f} minutes of "
            "training as measured on real scenes, plus loading; docs/run-time.md)")
