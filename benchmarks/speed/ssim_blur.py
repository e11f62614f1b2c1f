"""SSIM's Gaussian blur of the five local moments, forward + backward: kornia's separable filter against uw3dgs's.

    MALLOC_MMAP_MAX_=0 MALLOC_TRIM_THRESHOLD_=100000000000 python benchmarks/speed/ssim_blur.py --height 114
    python benchmarks/speed/ssim_blur.py --height 480

Blurs one [1, H, 1.5 H, 15] float32 stack (pred, gt, pred^2, gt^2, pred gt of an RGB pair: what `ssim` blurs) with
3DGS's 11-tap window and zero padding, and back-propagates a fixed gradient, one thread, best of `--repeats`.
kornia's `filter2d_separable` (border 'constant') is the same operation on a channels-first copy; uw3dgs's
`_gaussian_blur` convolves the channels-last view. Why uw3dgs keeps its own blur, with kornia as its test reference
(tests/test_library_references.py).
"""

from __future__ import annotations

from collections.abc import Callable

import kornia
import torch
from timing import compare_cli  # benchmarks/speed/timing.py, next to this script
from torch import Tensor

from uw3dgs.metrics.image import SSIM_SIGMA, SSIM_WINDOW, _gaussian_blur


def kornia_blur(images: Tensor) -> Tensor:
    taps = kornia.filters.get_gaussian_kernel1d(SSIM_WINDOW, SSIM_SIGMA, device=images.device, dtype=images.dtype)
    return kornia.filters.filter2d_separable(images.permute(0, 3, 1, 2), taps, taps, border_type="constant")


def blur_pass(blur: Callable[[Tensor], Tensor], height: int) -> tuple[Callable[[], None], list[Tensor]]:
    """One forward + backward of `blur` per call on fixed moments; the list holds the output and the gradient."""
    g = torch.Generator().manual_seed(0)
    images = torch.rand(1, height, height * 3 // 2, 15, generator=g).requires_grad_(True)
    upstream = torch.randn(1, 15, height, height * 3 // 2, generator=g)
    last: list[Tensor] = []

    def run() -> None:
        images.grad = None
        out = blur(images)
        out.backward(upstream)
        last[:] = [out.detach(), images.grad]

    return run, last


def main() -> None:
    compare_cli(__doc__, "--height", 114, "SSIM blur of {n} x 1.5 {n} x 15 moments, forward + backward, 1 thread",
                {"kornia filter2d_separable": kornia_blur, "channels-last conv (uw3dgs)": _gaussian_blur}, blur_pass)


if __name__ == "__main__":
    main()
