"""Differentiable rasterization of 3D Gaussians: `rasterize` is the entry point."""

from uw3dgs.render.rasterize import BACKENDS, rasterize, register_backend
from uw3dgs.render.types import RasterOutput, RasterSettings

__all__ = ["BACKENDS", "RasterOutput", "RasterSettings", "rasterize", "register_backend"]
