"""VM field reads as one compiled CPU kernel (`vm_field.cpp`).

`vm_read(u, fields)` is `VMField.forward` (twelve grid_samples, the basis product and the softplus in PyTorch) of
one or more fields of one shape at the same points, in one pass per point, with a hand-written backward to the
points and every factor: the same outputs and gradients to float rounding (tests/test_medium.py), deterministic
whatever the thread count. `MediumGrid` reads both its fields with it for CPU tensors of float32 or float64 when the
extension is built (`--model.medium.kernel compiled`, the default); the PyTorch path stays the reference, and the
path on CUDA (docs/performance.md, "The medium on CPU").
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
