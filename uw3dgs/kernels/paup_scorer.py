"""PAUP's scorer phi (`paup_scorer.cpp`): the floater probability m = sigmoid(phi(PUS)) of a 1 -> H -> 1 ReLU MLP, one
pass per Gaussian, with its backward to PUS and phi's weights."""

from __future__ import annotations

import torch
from torch import Tensor
from torch.autograd.function import once_differentiable

from uw3dgs.kernels.build import extension


class FloaterMLP(torch.autograd.Function):
    """phi and the sigmoid in one compiled pass per Gaussian (paup_scorer.cpp): the [N, H] hidden layer is
    never formed. The same numbers as the PyTorch path to float rounding (tests/test_paup.py)."""

    @staticmethod
    def forward(ctx, x, w1, b1, w2, b2):
        m = extension().floater_mlp_forward(x, w1, b1, w2, b2)
        ctx.save_for_backward(x, w1, b1, w2, b2, m)
        return m

    @staticmethod
    @once_differentiable
    def backward(ctx, grad):
        grads = extension().floater_mlp_backward(*ctx.saved_tensors, grad.contiguous())
        return tuple(g if needed else None for g, needed in zip(grads, ctx.needs_input_grad, strict=True))


def floater_probability(pus: Tensor, w1: Tensor, b1: Tensor, w2: Tensor, b2: Tensor) -> Tensor:
    """m [N] = sigmoid(w2 . relu(w1 pus_i + b1) + b2) of contiguous CPU tensors: pus [N], w1 [H], b1 [H], w2 [H],
    b2 [1]; gradients reach every input."""
    return FloaterMLP.apply(pus, w1, b1, w2, b2)
