"""Density control: how the set of Gaussians grows and shrinks during training (shaped like gsplat's
`strategy/`). A strategy takes the Gaussians, their optimizers and its own state, and knows nothing of the
trainer; a method wires it in with a training callback (`DensityControl`)."""

from uw3dgs.strategy.base import DensityEvents, ExtraPruning, GaussianParameters, OptimizerSurgery
from uw3dgs.strategy.callback import DensityControl
from uw3dgs.strategy.default import DefaultStrategy, DensificationConfig

__all__ = ["DefaultStrategy", "DensificationConfig", "DensityControl", "DensityEvents", "ExtraPruning",
           "GaussianParameters", "OptimizerSurgery"]
