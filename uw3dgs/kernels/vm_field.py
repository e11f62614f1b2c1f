"""VM field reads as one compiled CPU kernel (`vm_field.cpp`): the medium grid's fields (`vm_read`) and TensoRF's
plane x line products with a rank per mode over a box-shaped grid (`vm_products`).

`vm_read(u, fields)` is `VMField.forward` (twelve grid_samples, the basis product and the softplus in PyTorch) of
one or more fields of one shape at the same points, in one pass per point, with a hand-written backward to the
points and every factor: the same outputs and gradients to float rounding (tests/test_medium.py), deterministic
whatever the thread count. `MediumGrid` reads both its fields with it for CPU tensors of float32 or float64 when the
extension is built (`--model.medium.kernel compiled`, the default); the PyTorch path stays the reference, and the
path on CUDA (docs/performance.md, "The medium on CPU").

`vm_products(u, planes, lines, axes, summed)` is `fields/tensorf.py`'s `vm_products` (two grid_samples per mode,
then a concatenation or a sum) in one call, with a hand-written backward to the planes and lines (the points get no
gradient), deterministic whatever the thread count; `TensoRFField` reads with it on the same terms
(`--model.kernels compiled`); tests/test_vm_products.py compares it with grid_sample.
"""

from __future__ import annotations

from collections.abc import Sequence

import torch
from torch import Tensor
from torch.autograd.function import once_differentiable

from uw3dgs.kernels.build import extension

FACTORS = 4
"""A field's factors, in order: planes [3, R, G, G], lines [3, R, G], basis [C, 3R], bias [C]."""


class _VMRead(torch.autograd.Function):
    @staticmethod
    def forward(ctx, u, *factors):
        planes, lines, basis, bias = (list(factors[i::FACTORS]) for i in range(FACTORS))
        out, pre = extension().vm_fields_forward(u, planes, lines, basis, bias)
        ctx.save_for_backward(u, pre, *factors)  # the pre-activations: softplus's derivative without a re-read
        return out

    @staticmethod
    @once_differentiable
    def backward(ctx, grad_out):
        u, pre, *factors = ctx.saved_tensors
        planes, lines, basis, bias = (list(factors[i::FACTORS]) for i in range(FACTORS))
        g_u, *g_factors = extension().vm_fields_backward(u, planes, lines, basis, bias, pre,
                                                                         grad_out.contiguous())
        # per field, in the inputs' order: planes, lines, basis, bias
        grads = [g_u[0], *(g for field in zip(*g_factors, strict=True) for g in field)]
        return tuple(g if needed else None for g, needed in zip(grads, ctx.needs_input_grad, strict=True))


def vm_read(u: Tensor, fields: Sequence[tuple[Tensor, Tensor, Tensor, Tensor]]) -> Tensor:
    """softplus(basis @ features(u) + bias) of every field at points u [N, 3] in [-1, 1]^3 -> [N, F, C]. Each field
    is (planes [3, R, G, G], lines [3, R, G], basis [C, 3R], bias [C]) (VMField's factors, TensoRF's mode order
    XY x Z, XZ x Y, YZ x X), all fields of one shape."""
    factors = [t.to(u.dtype).contiguous() for field in fields for t in field]
    out = _VMRead.apply(u.contiguous(), *factors)
    return out.view(len(u), len(fields), -1)


class _VMProducts(torch.autograd.Function):
    @staticmethod
    def forward(ctx, u, axes, summed, *factors):
        modes = len(factors) // 2
        ctx.axes, ctx.summed = axes, summed
        ctx.save_for_backward(u, *factors)
        return extension().vm_products_forward(u, list(factors[:modes]), list(factors[modes:]), axes, summed)

    @staticmethod
    @once_differentiable
    def backward(ctx, grad_out):
        u, *factors = ctx.saved_tensors
        modes = len(factors) // 2
        grads = extension().vm_products_backward(u, factors[:modes], factors[modes:], ctx.axes, ctx.summed,
                                                 grad_out.contiguous())
        return (None, None, None, *(g if needed else None for g, needed in zip(grads, ctx.needs_input_grad[3:],
                                                                               strict=True)))


def vm_products(u: Tensor, planes: Sequence[Tensor], lines: Sequence[Tensor], axes: Sequence[tuple[int, int, int]],
                summed: bool = False) -> Tensor:
    """Per mode m, the products P_{m,r}(u) L_{m,r}(u) of its plane `planes[m]` [R_m, rows, columns], read bilinearly
    at (u[:, row axis], u[:, column axis]) (grid_sample's (y, x)), and its line `lines[m]` [R_m, length], read linearly
    at u[:, line axis], with `axes[m]` = (row axis, column axis, line axis); points u [N, 3] in [-1, 1]^3
    (align_corners=True coordinates, zero outside). Returns [N, sum_m R_m] mode by mode, or with `summed` their sum
    [N]. Differentiable in the planes and lines, not in u (an error if u requires a gradient)."""
    if u.requires_grad:
        raise ValueError("vm_products: the compiled read gives no gradient to the points; read with grid_sample "
                         "(fields/tensorf.py, --model.kernels torch) where the points need one")
    factors = [t.to(u.dtype).contiguous() for t in (*planes, *lines)]
    flat_axes = [int(a) for triple in axes for a in triple]
    return _VMProducts.apply(u.contiguous(), flat_axes, summed, *factors)
