"""Training callbacks: how a method hooks densification, pruning and schedules into the generic loop."""

from __future__ import annotations

from typing import Any, Protocol


class TrainingCallback:
    """Hooks the Trainer calls every step; override what you need. State is saved in checkpoints."""

    name: str = "callback"

    def before_step(self, step: int) -> None:
        """Before the forward pass (schedules: SH degree, learning rates)."""

    def after_backward(self, step: int, batch: dict[str, Any], outputs: dict[str, Any]) -> None:
        """Gradients exist, parameters not yet updated (read screen-space gradients here). `batch` is the
        view trained on (its 'camera' gives the image size and centre), `outputs` what the model rendered."""

    def after_step(self, step: int, batch: dict[str, Any], outputs: dict[str, Any]) -> None:
        """After the optimizer step (densify, prune, reset: parameters may change size here)."""

    def state_dict(self) -> dict[str, Any]:
        return {}

    def load_state_dict(self, state: dict[str, Any]) -> None:
        """Restore what `state_dict` returned."""


class Stepped(Protocol):
    def set_step(self, step: int) -> None: ...


class StepSchedule(TrainingCallback):
    """Tells a component whose behaviour follows the step (the SH degree, PAUP's start and refreshes) the step,
    before each forward pass; `name` keys its (empty) state in checkpoints."""

    def __init__(self, name: str, target: Stepped):
        self.name = name
        self.target = target

    def before_step(self, step: int) -> None:
        self.target.set_step(step)
