"""Spherical-harmonics colours: the compiled kernel (uw3dgs), one batched product in PyTorch, one term per function.

    MALLOC_MMAP_MAX_=0 MALLOC_TRIM_THRESHOLD_=100000000000 python benchmarks/speed/sh_eval.py
    python benchmarks/speed/sh_eval.py --gaussians 90000

Times forward + backward of the view-dependent colours of N Gaussians (degree 3, one thread, best of
`--repeats`) four ways and checks the first and last agree. The per-term sum over the concatenated
coefficients, sh[:, 0] * Y_0 + sh[:, 1] * Y_1 + ..., is how 3DGS writes it and how uw3dgs did until this
benchmark: under autograd every `sh[:, i]` gives a backward that allocates and accumulates a full
[N, 16, 3] gradient, 16 times per step. The middle way is one batched product with autograd's backward,
whose coefficient gradient (an outer product per Gaussian) runs as a slow batched matmul; uw3dgs's own
backward (`_BandProduct`) makes it a broadcast multiply: the PyTorch path (`--model.kernels torch`, the
reference, and the path on CUDA). The compiled kernel (uw3dgs/kernels/sh_colors.py) does directions, basis, product,
offset, clamp and their backward in one C++ pass per Gaussian. Whole training steps:
`benchmarks/speed/training_step.py`, `benchmarks/speed/step_profile.py`.
"""

from __future__ import annotations

from collections.abc import Callable

import torch
from timing import compare_cli  # benchmarks/speed/timing.py, next to this script
from torch import Tensor

from uw3dgs.kernels.sh_colors import sh_colors
from uw3dgs.render.sh import C0, _basis, eval_sh_split, num_sh_bases


def eval_sh_per_term(degree: int, dc: Tensor, rest: Tensor, dirs: Tensor) -> Tensor:
    """The per-basis-function sum over the concatenated coefficients (3DGS's form), the baseline."""
    sh = torch.cat([dc[:, None], rest], dim=1)
    result = 0.0
    for i, value in enumerate(_basis(degree, dirs)):
        result = result + value[..., None] * sh[..., i, :]
    return result


def eval_sh_autograd_product(degree: int, dc: Tensor, rest: Tensor, dirs: Tensor) -> Tensor:
    """One batched product with autograd's own backward (uw3dgs before `_BandProduct`): the coefficients'
    gradient, an outer product per Gaussian, then runs as a batched matmul."""
    basis = torch.stack(_basis(degree, dirs)[1:], dim=-1)
    return C0 * dc + (basis.unsqueeze(-2) @ rest[..., : num_sh_bases(degree) - 1, :]).squeeze(-2)


COMPILED = "compiled"
"""The way that computes the colours with the compiled kernel (sh_colors), directions and clamp included."""


def colour_pass(evaluate, n: int, seed: int = 0) -> tuple[Callable[[], None], list[Tensor]]:
    """Forward + backward of max(eval + 0.5, 0) for n random Gaussians, as GaussianField.colors computes it;
    the list holds the last call's colours and gradients."""
    g = torch.Generator().manual_seed(seed)
    sh0 = torch.randn(n, 1, 3, generator=g).requires_grad_()
    sh_rest = (0.1 * torch.randn(n, 15, 3, generator=g)).requires_grad_()
    means = torch.randn(n, 3, generator=g).requires_grad_()
    weights = torch.rand(n, 3, generator=g)
    last: list[Tensor] = []

    def run() -> None:
        for t in (sh0, sh_rest, means):
            t.grad = None
        center = torch.tensor([0.0, 0.0, -5.0])
        if evaluate is COMPILED:
            colours = sh_colors(means, center, sh0[:, 0], sh_rest, 3)
        else:
            dirs = torch.nn.functional.normalize(means - center, dim=-1)
            colours = (evaluate(3, sh0[:, 0], sh_rest, dirs) + 0.5).clamp_min(0.0)
        (colours * weights).sum().backward()
        last[:] = [colours.detach(), sh0.grad, sh_rest.grad, means.grad]

    return run, last


def main() -> None:
    compare_cli(__doc__, "--gaussians", 90_000, "colours of {n} Gaussians, forward + backward, degree 3, 1 thread",
                {"per term (3DGS)": eval_sh_per_term, "one product, autograd bwd": eval_sh_autograd_product,
                 "one product, own bwd (PyTorch)": eval_sh_split, "compiled kernel (uw3dgs)": COMPILED}, colour_pass)


if __name__ == "__main__":
    main()
