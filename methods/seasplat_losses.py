"""SeaSplat's loss terms (Yang et al. 2024), as their code computes them, on this project's image layout.

Images are [H, W, 3] in [0, 1] (their code: [3, H, W]); depth and alpha maps are [H, W]. Every function returns a
scalar tensor and keeps the autograd graph of its inputs; which inputs a caller detaches is the method's business
(`methods/seasplat.py`), as in their `train.py`.
"""

from __future__ import annotations

import math

import torch
import torch.nn.functional as F
from torch import Tensor


def depth_weighted_l1(pred: Tensor, target: Tensor, depth: Tensor) -> Tensor:
    """mean over pixels and channels of |z (pred - target)|: pred, target [H, W, 3], depth z [H, W] (their
    `depth_weighted_l1_loss`; the far pixels, which the water veils most, weigh most)."""
    return (depth[..., None] * (pred - target)).abs().mean()


def edge_aware_depth_smoothness(image: Tensor, depth: Tensor) -> Tensor:
    """mean |dz/dx e^(-dI/dx)| + mean |dz/dy e^(-dI/dy)| over neighbouring pixels: depth z [H, W], image I
    [H, W, 3], dI the channel mean of the signed forward difference (their `SmoothDepthLoss`, which weights by
    e^(-dI) of the signed difference, not of its absolute value: a darkening edge lets the depth jump, a brightening
    one penalises the jump more). Hence not kornia's `inverse_depth_smoothness_loss`, which weights by e^(-|dI|)
    (the same where the image only brightens: tests/test_library_references.py)."""
    depth_dx, depth_dy = depth.diff(dim=1), depth.diff(dim=0)
    image_dx, image_dy = image.diff(dim=1).mean(-1), image.diff(dim=0).mean(-1)
    return (depth_dx * torch.exp(-image_dx)).abs().mean() + (depth_dy * torch.exp(-image_dy)).abs().mean()


ALPHA_BACKGROUND_THRESHOLD = 0.2 * math.sqrt(3.0)
"""Their `AlphaBackgroundLoss` threshold: a pixel is 'background coloured' when its RGB distance to the background
colour is below 20% of the RGB cube's diagonal."""


def alpha_background(image: Tensor, background: Tensor, alpha: Tensor,
                     threshold: float = ALPHA_BACKGROUND_THRESHOLD) -> Tensor:
    """mean alpha over the pixels whose colour in `image` [H, W, 3] is within `threshold` (Euclidean RGB distance) of
    `background` [3]; 0 where no pixel is (their `AlphaBackgroundLoss`, RGB variant): Gaussians should not cover
    what looks like open water. Only `alpha` [H, W] should carry a gradient (their code detaches the others)."""
    near = (image - background).norm(dim=-1) < threshold
    if not bool(near.any()):
        return alpha.sum() * 0.0
    return alpha[near].abs().mean()


def gray_world(image: Tensor, target: float = 0.5) -> Tensor:
    """mean over channels of (mean over pixels of the channel - target)^2 (their `GrayWorldPriorLoss`): each colour
    channel of the restored image should average mid grey."""
    return (image.mean(dim=(0, 1)) - target).square().mean()


def saturation(image: Tensor, high: float = 0.7) -> Tensor:
    """mean of (max(-x, 0) + max(x - high, 0))^2 over every value x of `image` (their `RgbSaturationLoss`; they use
    high = 0.7 on the restored image)."""
    return (F.relu(-image) + F.relu(image - high)).square().mean()


def backscatter_loss(direct: Tensor, cost_ratio: float = 1000.0, smooth_l1_beta: float = 0.2) -> Tensor:
    """DeepSeeColor's backscatter loss (their `DarkChannelPriorLossV3`), on direct = I_gt - B: mean max(D, 0) +
    cost_ratio * mean SmoothL1_beta(max(-D, 0)). The positive part pulls the backscatter up toward the image (the
    darkest pixels are backscatter alone); the steep negative part forbids backscatter above the image."""
    positive = F.relu(direct).mean()
    negative = F.smooth_l1_loss(F.relu(-direct), torch.zeros_like(direct), beta=smooth_l1_beta)
    return cost_ratio * negative + positive


def normalized_depth(depth_sum: Tensor, alpha: Tensor, scale: float = 1.0, min_max: bool = True) -> Tensor:
    """The depth SeaSplat's formation and losses use, per image, as their `train.py` computes it: the composited
    camera-space z of the Gaussian centres `depth_sum` [H, W] (= sum_i w_i z_i, no background) divided by the
    coverage `alpha` [H, W]; pixels this leaves undefined (alpha = 0) take the largest defined value (1 where none is);
    divided by `scale`; then, with `min_max`, mapped to [0, 1] by this image's own minimum and maximum (divided by the
    maximum where they are equal). The minimum and maximum carry gradients, as theirs do."""
    covered = alpha > 0
    depth = depth_sum / torch.where(covered, alpha, torch.ones_like(alpha))
    fill = depth.detach()[covered].max() if bool(covered.any()) else depth.new_ones(())
    depth = torch.where(covered, depth, fill) / scale
    if not min_max:
        return depth
    low, high = depth.min(), depth.max()
    if bool(low != high):
        return (depth - low) / (high - low)
    return depth / high
