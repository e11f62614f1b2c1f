"""Differentiable rasterization of 3D Gaussians: `rasterize` is the entry point (`masked_l1`: PAUP's masked render and
its loss in one pass)."""

from uw3dgs.render.rasterize import BACKENDS, masked_l1, rasterize, register_backend
from uw3dgs.render.types import RasterOutput, RasterSettings, Splats

__all__ = ["BACKENDS", "RasterOutput", "RasterSettings", "Splats", "masked_l1", "rasterize", "register_backend"]
