"""The Gaussians' view-dependent colours as one compiled CPU kernel (`sh_colors.cpp`): max(SH(d) + 0.5, 0) with d
the unit direction from the camera centre, and the backward to the SH coefficients and the means, in one pass per
Gaussian. The same numbers as `eval_sh_split` and the clamp in PyTorch to float rounding (tests/test_fields.py);
`GaussianField.colors` uses it under `--model.kernels compiled` for CPU tensors, PyTorch elsewhere (the reference,
and the path on CUDA)."""

from __future__ import annotations

import torch
from torch import Tensor
from torch.autograd.function import once_differentiable

from uw3dgs.kernels.build import extension


class _SHColors(torch.autograd.Function):
    @staticmethod
    def forward(ctx, means, center, dc, rest, degree):
        ctx.save_for_backward(means, center, dc, rest)
        ctx.degree = degree
        return extension().sh_colors_forward(means, center, dc, rest, degree)

    @staticmethod
    @once_differentiable
    def backward(ctx, grad):
        means, center, dc, rest = ctx.saved_tensors
        g_means, g_dc, g_rest = extension().sh_colors_backward(means, center, dc, rest, ctx.degree,
                                                                               grad.contiguous())
        needs = ctx.needs_input_grad
        return (g_means if needs[0] else None, None, g_dc if needs[2] else None, g_rest if needs[3] else None, None)


def sh_colors(means: Tensor, camera_center: Tensor, dc: Tensor, rest: Tensor, degree: int) -> Tensor:
    """max(eval_sh_split(degree, dc, rest, normalize(means - camera_center)) + 0.5, 0) [N, 3]: means [N, 3], the
    camera centre [3], the degree-0 coefficients dc [N, 3] and the others rest [N, M, 3] (M >= (degree + 1)^2 - 1;
    those above the degree are not read and get a zero gradient)."""
    dtype = means.dtype
    center = camera_center.detach().to(dtype).reshape(3).contiguous()
    return _SHColors.apply(means.contiguous(), center, dc.to(dtype).contiguous(), rest.to(dtype).contiguous(),
                           int(degree))
