"""Adam's update of the Gaussians: PyTorch's fused kernel (uw3dgs) against its per-operation loop.

    MALLOC_MMAP_MAX_=0 MALLOC_TRIM_THRESHOLD_=100000000000 python benchmarks/speed/adam_fused.py
    python benchmarks/speed/adam_fused.py --gaussians 186000

Times one `Optimizers.step()` over a GaussianField's parameter groups (degree-3 SH: 59 floats per Gaussian,
3DGS's learning rates, eps 1e-15), one thread, best of `--repeats`, both ways, after the same gradients, and
checks the updated parameters agree. The loop (PyTorch's default on CPU) makes a pass over memory per
operation (moments, bias corrections, sqrt, division); the fused kernel makes one. Whole training steps:
`benchmarks/speed/training_step.py`.
"""

from __future__ import annotations

from collections.abc import Callable

import torch
from timing import compare_cli  # benchmarks/speed/timing.py, next to this script
from torch import Tensor

import uw3dgs.engine.optimizers as optimizers_module
from uw3dgs.engine.optimizers import Optimizers
from uw3dgs.fields.gaussians import GaussianField, GaussianFieldConfig
from uw3dgs.methods.gaussian_splatting import gaussian_optimizers

FUSABLE = optimizers_module._fusable


def never_fused(params: list) -> bool:
    return False


def adam_pass(n: int, seed: int = 0) -> tuple[Callable[[], None], list[Tensor]]:
    """One optimizer step of n Gaussians from fixed parameters, moments and gradients per call; the list holds
    the parameters after the last call."""
    g = torch.Generator().manual_seed(seed)
    field = GaussianField(GaussianFieldConfig(), torch.randn(n, 3, generator=g), torch.rand(n, 3, generator=g))
    groups = field.param_groups()
    optimizers = Optimizers(gaussian_optimizers(), groups, scene_extent=1.0, max_num_iterations=30_000)
    params = [p for ps in groups.values() for p in ps]
    start = [p.detach().clone() for p in params]
    grads = [torch.randn(p.shape, generator=g) for p in params]
    last: list[Tensor] = []

    def run() -> None:
        with torch.no_grad():
            for p, value, grad in zip(params, start, grads, strict=True):
                p.copy_(value)
                p.grad = grad
        optimizers.step()
        last[:] = [p.detach() for p in params]

    return run, last


def adam_pass_with(choice: Callable[[list], bool], n: int) -> tuple[Callable[[], None], list[Tensor]]:
    optimizers_module._fusable = choice  # Optimizers asks the module-level name when it builds its Adams
    return adam_pass(n)


def main() -> None:
    compare_cli(__doc__, "--gaussians", 186_000, "Adam step of {n} Gaussians, 1 thread",
                {"per-operation loop": never_fused, "fused (uw3dgs)": FUSABLE}, adam_pass_with)


if __name__ == "__main__":
    main()
