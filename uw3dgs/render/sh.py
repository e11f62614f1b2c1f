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


def eval_sh(degree: int, sh: Tensor, dirs: Tensor) -> Tensor:
    """Evaluate SH coefficients [N, B, 3] (B >= num_sh_bases(degree)) along unit dirs [N, 3] -> [N, 3].

    Only the first num_sh_bases(degree) coefficients are used, so a model can raise its active degree
    during training without reshaping its coefficients.
    """
    if not 0 <= degree <= MAX_DEGREE:
        raise ValueError(f"SH degree must be in [0, {MAX_DEGREE}], got {degree}")
    if sh.shape[-2] < num_sh_bases(degree):
        raise ValueError(f"degree {degree} needs {num_sh_bases(degree)} SH coefficients, got {sh.shape[-2]}")
    # one [N, B] basis times the coefficients in a single product: taking the coefficients one basis at a
    # time makes autograd build and add a full-size zero gradient per basis (16 at degree 3), which was the
    # largest cost of a CPU training step at 90k Gaussians
    basis = torch.stack(torch.broadcast_tensors(*_basis(degree, dirs)), dim=-1)
    return (basis[..., None] * sh[..., : basis.shape[-1], :]).sum(-2)


def rgb_to_sh(rgb: Tensor) -> Tensor:
    """Degree-0 coefficient whose colour (eval + 0.5) is `rgb`."""
    return (rgb - 0.5) / C0


def sh_to_rgb(sh: Tensor) -> Tensor:
    """Colour (eval + 0.5) of a degree-0 coefficient."""
    return sh * C0 + 0.5
