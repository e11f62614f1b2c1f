"""The ray-marching renderer shared by volumetric methods (NeRF-like fields): rays, samplers, an occupancy grid,
compositors and full-image rendering. Imports no plugin: a scene field is a `RadianceField` from the registry."""

from uw3dgs.raymarch.compositing import UnderwaterComposite, composite, composite_underwater
from uw3dgs.raymarch.field import RadianceField, RadianceFieldConfig
from uw3dgs.raymarch.occupancy import OccupancyGrid
from uw3dgs.raymarch.rays import RayBundle, camera_ray_bundle
from uw3dgs.raymarch.samplers import BoxSampler, NDCSampler, RaySamples

__all__ = ["BoxSampler", "NDCSampler", "OccupancyGrid", "RadianceField", "RadianceFieldConfig", "RayBundle",
           "RaySamples", "UnderwaterComposite", "camera_ray_bundle", "composite", "composite_underwater"]
