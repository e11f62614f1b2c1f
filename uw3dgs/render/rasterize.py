"""The one rasterization entry point, dispatching to a registry of backends.

Every backend is a `RasterFn` (splats, camera, settings, projection) and must match `rasterize_reference`
numerically (the tests compare against it). Backends register with the device types they run on and a priority; 'auto'
picks the highest-priority backend for the device of the Gaussians.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import Tensor

from uw3dgs.cameras import Camera
from uw3dgs.kernels import compositing
from uw3dgs.render import gsplat_backend
from uw3dgs.render.cpu_backend import rasterize_cpu
from uw3dgs.render.reference import rasterize_reference
from uw3dgs.render.types import RasterFn, RasterOutput, RasterSettings, Splats


@dataclass(frozen=True)
class Backend:
    """A registered rasterizer; calling it calls `fn`."""

    fn: RasterFn
    devices: frozenset[str]
    """torch device types it runs on ('cpu', 'cuda', ...)."""
    priority: int
    """'auto' prefers higher priorities."""

    def __call__(self, splats: Splats, camera: Camera, settings: RasterSettings,
                 projection: RasterOutput | None = None) -> RasterOutput:
        return self.fn(splats, camera, settings, projection)


BACKENDS: dict[str, Backend] = {}


def register_backend(name: str, fn: RasterFn, devices: tuple[str, ...], priority: int = 0) -> None:
    """Make `fn` available as `RasterSettings(backend=name)` on the given device types."""
    BACKENDS[name] = Backend(fn=fn, devices=frozenset(devices), priority=priority)


def select_backend(name: str, device: torch.device) -> str:
    """Resolve a settings.backend value ('auto' or a registered name) for tensors on `device`."""
    usable = sorted(
        (n for n, b in BACKENDS.items() if device.type in b.devices),
        key=lambda n: -BACKENDS[n].priority,
    )
    if name == "auto":
        if not usable:
            raise ValueError(f"no rasterizer backend runs on {device.type}; registered: {sorted(BACKENDS)}")
        if device.type == "cuda" and usable[0] == "torch" and "gsplat" not in BACKENDS:
            gsplat_backend.warn_gsplat_missing()  # once: how to install the fast CUDA backend
        return usable[0]
    if name not in BACKENDS:
        raise ValueError(f"unknown rasterizer backend {name!r}; available: {['auto', *sorted(BACKENDS)]}")
    if name not in usable:
        raise ValueError(f"rasterizer backend {name!r} does not run on {device.type}; there use: {usable}")
    return name


def rasterize(splats: Splats, camera: Camera, settings: RasterSettings = RasterSettings(),
              projection: RasterOutput | None = None) -> RasterOutput:
    """Render one view of activated Gaussians (`Splats`; see `rasterize_reference` for shapes and conventions).

    Returns a [H, W, C] render and [H, W] alpha and depth, with no background: compose with
    render + (1 - alpha[..., None]) * background.

    `projection`: an earlier render of the same Gaussians (means, quats, scales) from the same camera whose
    opacities were at least these, e.g. the full render before PAUP's masked one. Its screen-space Gaussians
    are used as they are instead of projecting again; the outputs are the same as without it (its radii, from
    the larger opacities, bound the footprints, and every pixel is still tested against `opacities`), but no
    gradient reaches means, quats or scales, so they must not require one.
    """
    if projection is not None and any(t.requires_grad for t in (splats.means, splats.quats, splats.scales)):
        raise ValueError("a reused projection carries no gradient to means, quats or scales: render them detached "
                         "(frozen) or without `projection`")
    backend = BACKENDS[select_backend(settings.backend, splats.means.device)]
    return backend(splats, camera, settings, projection)


def masked_l1(projection: RasterOutput, opacities: Tensor, features: Tensor, target: Tensor, camera: Camera,
              settings: RasterSettings = RasterSettings()) -> tuple[Tensor, Tensor] | None:
    """PAUP's masked render and its loss in one pass: (render [H, W, C], mean |target - render|), the Gaussians of
    `projection` (an earlier render of this view, its screen-space Gaussians and tile lists reused; the same rule
    as `rasterize`'s `projection`) with `opacities` [N] (at most the earlier ones) and `features` [N, C], frozen:
    the mean carries a gradient to `opacities` only, the render none. The same numbers, to float rounding, as
    `rasterize` with that projection followed by the mean (tests/test_cpu_backend.py), without keeping the
    render's trace for a backward. None where the selected backend has no fused pass (all but 'cpu'): render and
    take the mean instead."""
    if select_backend(settings.backend, opacities.device) != "cpu":
        return None
    return compositing.masked_l1(projection, opacities, features, target, camera.width, camera.height, settings)


register_backend("torch", rasterize_reference, devices=("cpu", "cuda", "mps"), priority=0)
# Compiled C++/OpenMP backend, the default on CPU: built on first use (falls back to the reference with one
# warning if the build fails).
register_backend("cpu", rasterize_cpu, devices=("cpu",), priority=10)
# gsplat CUDA rasterizer, the default on CUDA when the optional extra is installed (pip install uw3dgs[cuda]).
# Only looked up here: gsplat is imported (and builds its kernels) on first use.
if gsplat_backend.gsplat_installed():
    register_backend("gsplat", gsplat_backend.rasterize_gsplat, devices=("cuda",), priority=20)
