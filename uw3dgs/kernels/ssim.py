"""SSIM as one compiled CPU kernel with its backward to the prediction (`ssim.cpp`): the map of
`uw3dgs.metrics.image.ssim` (3DGS's window and constants) in a few passes over memory. The same numbers as the
PyTorch path to float rounding, deterministic whatever the thread count (tests/test_metrics.py). The D-SSIM training
loss uses it under `--model.kernels compiled` (the default) for CPU images; PyTorch elsewhere: the reference, the path
on CUDA and the one evaluation uses."""

from __future__ import annotations

import torch
from torch import Tensor
from torch.autograd.function import once_differentiable

from uw3dgs.kernels.build import extension


class _SSIMSum(torch.autograd.Function):
    """The SSIM map summed per image [B] of pred [B, H, W, C] against gt; gradients reach pred only."""

    @staticmethod
    def forward(ctx, pred, gt, taps, c1, c2):
        ext = extension()
        out = ext.ssim_forward(pred, gt, taps, c1, c2, ctx.needs_input_grad[0])
        if ctx.needs_input_grad[0]:
            ctx.save_for_backward(pred, gt, taps, out[1])
        return out[0]

    @staticmethod
    @once_differentiable
    def backward(ctx, grad_sum):
        pred, gt, taps, derivatives = ctx.saved_tensors
        g_pred = extension().ssim_backward(pred, gt, derivatives, taps, grad_sum)
        return g_pred, None, None, None, None


def ssim_compiled(pred: Tensor, gt: Tensor, taps: Tensor, c1: float, c2: float) -> Tensor:
    """Mean SSIM per image [B] of pred, gt [B, H, W, C] (channels-last) with the 1D window `taps` (odd length,
    symmetric, normalised) and the stabilisers c1, c2. No gradient reaches gt (`ssim` sends a gt that needs one to
    the PyTorch path)."""
    dtype = pred.dtype
    pred, gt = pred.contiguous(), gt.detach().to(dtype).contiguous()
    total = _SSIMSum.apply(pred, gt, taps.to(dtype).contiguous(), float(c1), float(c2))
    return total / (pred.shape[1] * pred.shape[2] * pred.shape[3])
