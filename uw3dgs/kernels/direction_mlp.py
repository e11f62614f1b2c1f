"""The direction medium's MLP and its output activations as one compiled CPU kernel (`direction_mlp.cpp`): one
hidden layer of sigmoid units, then c_med = sigmoid, sigma_bs, sigma_attn = softplus(+ density_bias), packed [P, 9],
with the backward to the weights in one pass per block of pixels. The same numbers as the module's `nn.Sequential`
and PyTorch's activations to float rounding (tests/test_direction_mlp.py); `DirectionMedium` uses it under
`--model.kernels compiled` for CPU tensors, PyTorch elsewhere (the reference, and the path on CUDA)."""

from __future__ import annotations

import torch
from torch import Tensor
from torch.autograd.function import once_differentiable

from uw3dgs.kernels.build import extension


class _DirectionMLP(torch.autograd.Function):
    @staticmethod
    def forward(ctx, x, w1, b1, w2, b2, density_bias, for_backward):
        out, raw, hidden = extension().direction_mlp_forward(x, w1, b1, w2, b2, density_bias, for_backward)
        ctx.save_for_backward(x, w1, b1, w2, b2, raw, hidden)
        ctx.density_bias = density_bias
        return out

    @staticmethod
    @once_differentiable
    def backward(ctx, grad):
        x, w1, b1, w2, b2, raw, hidden = ctx.saved_tensors
        grads = extension().direction_mlp_backward(x, w1, b1, w2, b2, raw, hidden, grad.contiguous(),
                                                   ctx.density_bias)
        needs = ctx.needs_input_grad[1:5]
        return (None, *(g if needed else None for g, needed in zip(grads, needs, strict=True)), None, None)


def direction_mlp(x: Tensor, w1: Tensor, b1: Tensor, w2: Tensor, b2: Tensor, density_bias: float) -> Tensor:
    """[P, 9]: sigmoid of the first 3 and softplus(+ `density_bias`) of the other 6 of w2 sigmoid(w1 x + b1) + b2,
    for x [P, IN] (IN 1, 4, 9 or 16: an SH encoding), w1 [H, IN], b1 [H], w2 [9, H], b2 [9], contiguous CPU tensors
    of one dtype. Gradients reach the weights; x, the encoding of fixed ray directions, must need none."""
    if x.requires_grad:
        raise ValueError("direction_mlp gives no gradient to its input x: detach it, or use the PyTorch MLP")
    weights = (w1, b1, w2, b2)
    for_backward = torch.is_grad_enabled() and any(w.requires_grad for w in weights)
    return _DirectionMLP.apply(x.contiguous(), *(w.contiguous() for w in weights), float(density_bias), for_backward)
