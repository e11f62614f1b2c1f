"""The training callback that runs a density-control strategy in the Trainer's loop."""

from __future__ import annotations

from typing import Any

from uw3dgs.data.datamanager import Batch
from uw3dgs.engine.callbacks import TrainingCallback
from uw3dgs.engine.optimizers import Optimizers
from uw3dgs.strategy.base import ExtraPruning, GaussianParameters
from uw3dgs.strategy.default import DefaultStrategy
from uw3dgs.utils.profiling import section


class DensityControl(TrainingCallback):
    """Runs a density-control strategy in the training loop; its statistics are checkpointed."""

    name = "densification"

    def __init__(self, strategy: DefaultStrategy, gaussians: GaussianParameters, optimizers: Optimizers,
                 extra_pruning: ExtraPruning | None = None):
        self.strategy = strategy
        self.gaussians = gaussians
        self.optimizers = optimizers
        self.extra_pruning = extra_pruning
        """Another criterion pruning at the same events (PAUP); its per-Gaussian state follows every change."""
        self.state = strategy.initialize_state(gaussians)

    @section("densification")
    def after_backward(self, step: int, batch: Batch, outputs: dict[str, Any]) -> None:
        camera = outputs.get("camera", batch["camera"])  # the one rendered, where a method renders another size
        self.strategy.step_post_backward(self.state, step, outputs["means2d"], outputs["radii"],
                                         (camera.width, camera.height), outputs.get("absgrad"))

    @section("densification")
    def after_step(self, step: int, batch: Batch, outputs: dict[str, Any]) -> None:
        extra, strategy = self.extra_pruning, self.strategy
        remove = extra.select(step) if extra is not None and extra.prunes_at(step, strategy) else None
        origin = strategy.step_post_optimizer(self.gaussians, self.optimizers, self.state, step, remove)
        if extra is not None and origin is not None:
            extra.reindex(origin)

    def state_dict(self) -> dict[str, Any]:
        return dict(self.state)

    def load_state_dict(self, state: dict[str, Any]) -> None:
        device = self.gaussians.means.device
        self.state = {name: value.clone().to(device) for name, value in state.items()}
