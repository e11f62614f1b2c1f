"""Depth metrics against a ground-truth range map (scenes that have one: the synthetic ones)."""

from __future__ import annotations

from torch import Tensor

COVERED = 0.5
"""A pixel's rendered range counts where the Gaussians cover more than this share of it (alpha)."""


def range_abs_rel(pred: Tensor, alpha: Tensor, truth: Tensor) -> float | None:
    """Mean |pred - truth| / truth over pixels with a true surface (finite range) that the render covers.

    pred, alpha, truth: [H, W]. Open water (infinite true range) and pixels with alpha <= COVERED are left
    out: their rendered range is not a surface. None when no pixel qualifies (nothing to average).
    """
    valid = truth.isfinite() & (alpha > COVERED)
    if not bool(valid.any()):
        return None
    return float(((pred[valid] - truth[valid]).abs() / truth[valid]).mean())
