"""Image-quality metrics and photometric losses on channels-last images in [0, 1].

Images are [H, W, C] or batched [B, H, W, C] (C = 3 for RGB), the layout renders and datasets use.
Metrics return one value per image; benchmark tables average per image first, then over images,
as the 3DGS papers do.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import Tensor

from uw3dgs.kernels.policy import Kernels, use_compiled
from uw3dgs.kernels.ssim import ssim_compiled

MSE_FLOOR = 1e-10
"""PSNR uses max(mse, MSE_FLOOR), so identical images score 100 dB instead of inf and means stay finite."""

SSIM_WINDOW = 11
"""Side of the Gaussian SSIM window in pixels (3DGS, after Wang et al. 2004)."""
SSIM_SIGMA = 1.5
"""Standard deviation of the Gaussian SSIM window in pixels."""
SSIM_C1 = 0.01**2
"""Stabiliser of SSIM's luminance term, (K1 L)^2 with K1 = 0.01 and dynamic range L = 1."""
SSIM_C2 = 0.03**2
"""Stabiliser of SSIM's contrast-structure term, (K2 L)^2 with K2 = 0.03 and L = 1."""


def _check_pair(pred: Tensor, gt: Tensor) -> None:
    """Fail early with a readable message instead of a broadcasting surprise deep in a conv."""
    if pred.shape != gt.shape:
        raise ValueError(f"pred and gt shapes differ: {tuple(pred.shape)} vs {tuple(gt.shape)}")
    if pred.ndim not in (3, 4):
        raise ValueError(f"expected [H, W, C] or [B, H, W, C] images, got shape {tuple(pred.shape)}")


def psnr(pred: Tensor, gt: Tensor, mask: Tensor | None = None) -> Tensor:
    """Peak signal-to-noise ratio in dB for images in [0, 1] (peak 1), one value per image.

    Returns a 0-dim tensor for [H, W, C] inputs and a [B] tensor for [B, H, W, C] inputs. Inputs are
    not clamped: clamp renders to [0, 1] before evaluating, as the 3DGS evaluation does. `mask` [H, W] or
    [B, H, W] (bool) restricts the mean squared error to its pixels (masked PSNR); an empty mask is an error.
    """
    _check_pair(pred, gt)
    squared = (pred - gt).square().mean(dim=-1)
    if mask is None:
        mse = squared.mean(dim=(-2, -1))
    else:
        if mask.shape != squared.shape:
            raise ValueError(f"mask shape {tuple(mask.shape)} does not match the images' {tuple(squared.shape)}")
        count = mask.sum(dim=(-2, -1))
        if bool((count == 0).any()):
            raise ValueError("masked PSNR of an empty mask is undefined")
        mse = (squared * mask).sum(dim=(-2, -1)) / count
    return -10.0 * torch.log10(mse.clamp_min(MSE_FLOOR))


def _gaussian_window(dtype: torch.dtype, device: torch.device) -> Tensor:
    """Normalised 1D Gaussian taps; their outer product is 3DGS's normalised 2D window."""
    offsets = torch.arange(SSIM_WINDOW, dtype=torch.float64) - SSIM_WINDOW // 2
    taps = torch.exp(-(offsets**2) / (2.0 * SSIM_SIGMA**2))
    return (taps / taps.sum()).to(dtype=dtype, device=device)


def _gaussian_blur(images: Tensor) -> Tensor:
    """Blur [B, H, W, C] per channel with zero padding ('same' size); returns [B, C, H, W].

    Equal to 3DGS's 2D F.conv2d(padding=5, groups=C), but as two 1D passes (the window is separable
    and zero padding commutes with it). The channels-last permute is a view, which keeps the
    depthwise convs on PyTorch's fast channels-last path: kornia's `filter2d_separable` (border 'constant') gives
    the same numbers (the tests' reference) but several times slower (benchmarks/speed/ssim_blur.py).
    """
    channels = images.shape[-1]
    taps = _gaussian_window(images.dtype, images.device)
    radius = SSIM_WINDOW // 2
    vertical = taps.view(1, 1, -1, 1).expand(channels, 1, -1, 1)
    horizontal = taps.view(1, 1, 1, -1).expand(channels, 1, 1, -1)
    x = F.conv2d(images.permute(0, 3, 1, 2), vertical, padding=(radius, 0), groups=channels)
    return F.conv2d(x, horizontal, padding=(0, radius), groups=channels)


def ssim_map(pred: Tensor, gt: Tensor) -> Tensor:
    """The SSIM map [B, C, H, W] of images [B, H, W, C] (3DGS's window and constants, per-channel zero-padded
    'same' filtering): `ssim` before its mean, in PyTorch. Its pixels at least 5 (the window's radius) from every
    border see no padding: there it is the map of kornia's and scikit-image's SSIM, which pad otherwise."""
    _check_pair(pred, gt)
    if pred.ndim != 4:
        raise ValueError(f"ssim_map takes batched [B, H, W, C] images, got shape {tuple(pred.shape)}")
    channels = pred.shape[-1]
    # One blur pass over all five local moments instead of five separate convolutions.
    moments = _gaussian_blur(torch.cat([pred, gt, pred * pred, gt * gt, pred * gt], dim=-1))
    mu1, mu2, mean11, mean22, mean12 = moments.split(channels, dim=1)
    mu1_sq, mu2_sq, mu1_mu2 = mu1 * mu1, mu2 * mu2, mu1 * mu2
    sigma1_sq = mean11 - mu1_sq
    sigma2_sq = mean22 - mu2_sq
    sigma12 = mean12 - mu1_mu2
    return ((2.0 * mu1_mu2 + SSIM_C1) * (2.0 * sigma12 + SSIM_C2)) / (
        (mu1_sq + mu2_sq + SSIM_C1) * (sigma1_sq + sigma2_sq + SSIM_C2)
    )


def ssim(pred: Tensor, gt: Tensor, kernel: Kernels = "torch") -> Tensor:
    """Structural similarity exactly as the 3DGS codebase computes it, one value per image.

    11x11 Gaussian window (sigma 1.5), C1 = 0.01^2, C2 = 0.03^2, per-channel zero-padded 'same'
    filtering, and the mean of the SSIM map over pixels and channels. Differentiable, so it also
    drives the D-SSIM training loss. Returns a 0-dim tensor for [H, W, C] and [B] for [B, H, W, C].
    `kernel` 'compiled': the compiled CPU kernel (uw3dgs/kernels/ssim.py) for CPU images of float32 or float64 when
    it is built and gt needs no gradient; else this PyTorch path, the reference.
    """
    _check_pair(pred, gt)
    batched = pred.ndim == 4
    if not batched:
        pred, gt = pred[None], gt[None]
    if use_compiled(kernel, pred) and gt.device.type == "cpu" and not gt.requires_grad:
        taps = _gaussian_window(pred.dtype, pred.device)
        per_image = ssim_compiled(pred, gt, taps, SSIM_C1, SSIM_C2)
        return per_image if batched else per_image[0]
    per_image = ssim_map(pred, gt).mean(dim=(1, 2, 3))
    return per_image if batched else per_image[0]


def dssim_loss(pred: Tensor, gt: Tensor, kernel: Kernels = "torch") -> Tensor:
    """D-SSIM training term 1 - SSIM (3DGS's convention, not (1 - SSIM) / 2), averaged over images; `kernel` as
    in `ssim`."""
    return 1.0 - ssim(pred, gt, kernel).mean()


def l1_loss(pred: Tensor, gt: Tensor) -> Tensor:
    """Mean absolute error over all pixels and channels: 3DGS's photometric L1 term."""
    _check_pair(pred, gt)
    return (pred - gt).abs().mean()
