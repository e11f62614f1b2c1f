"""Real spherical harmonics up to degree 3, with the constants and sign conventions of 3DGS.

The basis is the real SH basis with the Condon-Shortley phase, ordered l = 0..3, m = -l..l.
`eval_sh` returns the raw expansion; 3DGS colours are max(eval_sh(...) + 0.5, 0), and that offset
and clamp are the caller's job.
"""

from __future__ import annotations

import torch
from torch import Tensor

C0 = 0.28209479177387814
C1 = 0.4886025119029199
C2 = (1.0925484305920792, -1.0925484305920792, 0.31539156525252005, -1.0925484305920792, 0.5462742152960396)
C3 = (
    -0.5900435899266435,
    2.890611442640554,
    -0.4570457994644658,
    0.3731763325901154,
    -0.4570457994644658,
    1.445305721320277,
    -0.5900435899266435,
)
MAX_DEGREE = 3


def num_sh_bases(degree: int) -> int:
    """Coefficients per channel for SH up to `degree`."""
    return (degree + 1) ** 2


def _basis(degree: int, dirs: Tensor) -> list[Tensor]:
    """The first num_sh_bases(degree) basis functions at unit directions [N, 3], each [N]."""
    x, y, z = dirs.unbind(-1)
    basis = [C0 * x.new_ones(())]
    if degree >= 1:
        basis += [-C1 * y, C1 * z, -C1 * x]
    if degree >= 2:
        xx, yy, zz = x * x, y * y, z * z
        basis += [
            C2[0] * x * y,
            C2[1] * y * z,
            C2[2] * (2.0 * zz - xx - yy),
            C2[3] * x * z,
            C2[4] * (xx - yy),
        ]
    if degree >= 3:
        basis += [
            C3[0] * y * (3.0 * xx - yy),
            C3[1] * x * y * z,
            C3[2] * y * (4.0 * zz - xx - yy),
            C3[3] * z * (2.0 * zz - 3.0 * xx - 3.0 * yy),
            C3[4] * x * (4.0 * zz - xx - yy),
            C3[5] * z * (xx - yy),
            C3[6] * x * (xx - 3.0 * yy),
        ]
    return basis


def sh_basis(degree: int, dirs: Tensor) -> Tensor:
    """The real SH basis up to `degree` at unit directions [..., 3]: [..., num_sh_bases(degree)] (an encoding)."""
    return torch.stack(torch.broadcast_tensors(*_basis(degree, dirs)), dim=-1)


def eval_sh(degree: int, sh: Tensor, dirs: Tensor) -> Tensor:
    """Evaluate SH coefficients [N, B, 3] (B >= num_sh_bases(degree)) along unit dirs [N, 3] -> [N, 3].

    Only the first num_sh_bases(degree) coefficients are used, so a model can raise its active degree
    during training without reshaping its coefficients.
    """
    return eval_sh_split(degree, sh[..., 0, :], sh[..., 1:, :], dirs)


def eval_sh_split(degree: int, dc: Tensor, rest: Tensor, dirs: Tensor) -> Tensor:
    """`eval_sh` with the degree-0 coefficient [N, 3] apart from the others [N, B - 1, 3], as the Gaussians
    store them: no per-step concatenation.

    The higher bands are one batched product, basis [N, 1, B - 1] @ coefficients [N, B - 1, 3]. Written as
    one term per basis function (3DGS's form), autograd builds and adds a full-size zero gradient per term:
    a large share of a CPU training step (docs/performance.md, benchmarks/speed/sh_eval.py).
    """
    if not 0 <= degree <= MAX_DEGREE:
        raise ValueError(f"SH degree must be in [0, {MAX_DEGREE}], got {degree}")
    n = num_sh_bases(degree)
    if rest.shape[-2] + 1 < n:
        raise ValueError(f"degree {degree} needs {n} SH coefficients, got {rest.shape[-2] + 1}")
    value = C0 * dc
    if degree == 0:
        return value
    basis = torch.stack(_basis(degree, dirs)[1:], dim=-1)
    return value + _BandProduct.apply(basis, rest[..., : n - 1, :])


class _BandProduct(torch.autograd.Function):
    """basis [N, K] x coefficients [N, K, 3] -> [N, 3], one batched product per Gaussian.

    Autograd's own backward of that product forms the coefficients' gradient, an outer product per Gaussian,
    as a batched matmul of [K, 1] by [1, 3], much slower on CPU than the broadcast multiply used here, with
    bitwise the same values (each entry is one product either way); timings in docs/performance.md."""

    @staticmethod
    def forward(ctx, basis: Tensor, coeffs: Tensor) -> Tensor:
        ctx.save_for_backward(basis, coeffs)
        return (basis.unsqueeze(-2) @ coeffs).squeeze(-2)

    @staticmethod
    def backward(ctx, grad: Tensor) -> tuple[Tensor | None, Tensor | None]:
        basis, coeffs = ctx.saved_tensors
        grad_basis = (coeffs @ grad.unsqueeze(-1)).squeeze(-1) if ctx.needs_input_grad[0] else None
        grad_coeffs = basis.unsqueeze(-1) * grad.unsqueeze(-2) if ctx.needs_input_grad[1] else None
        return grad_basis, grad_coeffs


def rgb_to_sh(rgb: Tensor) -> Tensor:
    """Degree-0 coefficient whose colour (eval + 0.5) is `rgb`."""
    return (rgb - 0.5) / C0


def sh_to_rgb(sh: Tensor) -> Tensor:
    """Colour (eval + 0.5) of a degree-0 coefficient."""
    return sh * C0 + 0.5
