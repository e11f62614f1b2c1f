"""`rasterize_medium`: one view rendered with the water composited between the depth-sorted Gaussians (WaterSplatting's
compositing), on the compiled CPU kernel where it runs, else on the PyTorch reference.

gsplat has no such compositor: on CUDA this runs the PyTorch reference (correct, much slower than gsplat's 3DGS
compositing) and says so once.
"""

from __future__ import annotations

import warnings

from uw3dgs.cameras import Camera
from uw3dgs.kernels import medium_compositing as medium_cpu
from uw3dgs.render.medium_reference import rasterize_medium_reference
from uw3dgs.render.medium_types import MediumRasterOutput, PixelMedium
from uw3dgs.render.types import RasterSettings, Splats

_warned: set[str] = set()



def warn_reference_on(device_type: str) -> None:
    """One warning per process and device type: the medium compositor runs the PyTorch reference there."""
    if device_type in _warned:
        return
    _warned.add(device_type)
    warnings.warn(f"uw3dgs: the medium compositor (watersplatting's water between Gaussians) has no {device_type} "
                  "kernel (gsplat cannot composite a medium between Gaussians); it runs the PyTorch reference there, "
                  "correct but much slower than a 3DGS render", RuntimeWarning, stacklevel=3)


def rasterize_medium(splats: Splats, medium: PixelMedium, camera: Camera, settings: RasterSettings = RasterSettings(),
                     absgrad: bool = False) -> MediumRasterOutput:
    """Render one view of activated Gaussians (`splats`, features = colours [N, 3]) with the per-pixel water `medium`
    ([H, W, 3] each); see `MediumRasterOutput` for the outputs.

    `settings.backend`: 'auto' takes the compiled CPU kernel where it runs (CPU float tensors, the extension built),
    else the reference; 'torch' the reference; 'cpu' the compiled kernel (an error where it does not run); 'gsplat'
    is an error (gsplat has no medium compositor). `absgrad`: fill the output's `absgrad` [N, 2] in the backward
    (absolute-gradient densification)."""
    backend = settings.backend
    if backend == "gsplat":
        raise ValueError("--model.raster.backend gsplat: gsplat has no compositor with a medium between Gaussians; "
                         "use auto (the compiled CPU kernel, else the PyTorch reference) or torch")
    if backend not in ("auto", "torch", "cpu"):
        raise ValueError(f"--model.raster.backend {backend}: the medium compositor runs on auto, torch or cpu")
    usable = backend != "torch" and medium_cpu.takes(splats.means, settings)
    if backend == "cpu" and not usable:
        raise ValueError("--model.raster.backend cpu: the compiled medium compositor does not run here (CPU float32 "
                         "or float64 tensors and a built extension needed); use auto or torch")
    if backend != "torch" and usable:
        return medium_cpu.rasterize_medium_cpu(splats, medium, camera, settings, absgrad=absgrad)
    if splats.means.device.type != "cpu":
        warn_reference_on(splats.means.device.type)
    return rasterize_medium_reference(splats, medium, camera, settings, absgrad=absgrad)
