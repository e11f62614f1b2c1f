"""What a density-control strategy needs of the Gaussians and of their optimizers (structural types)."""

from __future__ import annotations

from collections.abc import Callable
from typing import Protocol

from torch import Tensor, nn


class GaussianParameters(Protocol):
    """Per-Gaussian parameters, all with N rows: `means` [N, 3], `scales` [N, 3] (log), `quats` [N, 4],
    `opacities` [N] (logit), and whatever else the field keeps per Gaussian (colours), all named in
    `param_names`."""

    param_names: tuple[str, ...]
    means: nn.Parameter
    scales: nn.Parameter
    quats: nn.Parameter
    opacities: nn.Parameter

    def set_params(self, values: dict[str, Tensor]) -> dict[str, tuple[nn.Parameter, nn.Parameter]]:
        """Replace parameters by new tensors; returns name -> (old parameter, new parameter)."""
        ...


class OptimizerSurgery(Protocol):
    """Optimizers whose per-parameter state follows a parameter that changes size."""

    def replace_param(self, name: str, old: nn.Parameter, new: nn.Parameter,
                      moments_fn: Callable[[Tensor], Tensor]) -> None:
        """Swap `old` for `new` in group `name`, mapping each Adam moment with `moments_fn`."""
        ...


class DensityEvents(Protocol):
    """When a density-control strategy densifies, and when after that it may still prune (`DefaultStrategy`)."""

    def is_refine_step(self, step: int) -> bool:
        ...

    def is_late_prune_step(self, step: int) -> bool:
        ...


class ExtraPruning(Protocol):
    """A second pruning criterion run by density control (PAUP), at its events or on its own cadence, with
    per-Gaussian state that must follow the Gaussians when they are cloned, split or removed."""

    def prunes_at(self, step: int, strategy: DensityEvents) -> bool:
        """Whether it prunes at `step` (then `select` is called): at `strategy`'s events, or on its own cadence
        (outside an event the Gaussians it selects are pruned alone)."""
        ...

    def select(self, step: int) -> Tensor | None:
        """[N] bool: the Gaussians to remove at this event, or None for none."""
        ...

    def reindex(self, origin: Tensor) -> None:
        """The Gaussians changed: `origin` [N'] (long) gives each one's index before, -1 for new ones."""
        ...
