"""Evaluation numbers every method with a medium reports: its restored image against the clean truth, and its learned
medium (and the error against the true one) under the eval JSON's key names (DESIGN.md: `uri_*`, `beta_d_r|g|b`,
`beta_b_r|g|b`, `b_inf_r|g|b`, `*_rel_error`)."""

from __future__ import annotations

from typing import Any

from torch import Tensor

from uw3dgs.data.scene import SceneData
from uw3dgs.metrics.image import psnr, ssim
from uw3dgs.metrics.lpips import lpips_metrics


def restored_image_metrics(uri: Tensor, batch: dict[str, Any]) -> dict[str, float | None]:
    """`uri_psnr`, `uri_ssim`, `uri_lpips_*` (and `uri_psnr_covisible`) of the restored image `uri` [H, W, 3] against
    the batch's 'clean_image'; empty where the dataset has no clean image."""
    if "clean_image" not in batch:
        return {}
    uri, clean = uri.detach().clamp(0, 1), batch["clean_image"]
    metrics: dict[str, float | None] = {"uri_psnr": float(psnr(uri, clean)), "uri_ssim": float(ssim(uri, clean))}
    metrics.update(lpips_metrics(uri, clean, prefix="uri_"))
    if "covisible" in batch:
        metrics["uri_psnr_covisible"] = float(psnr(uri, clean, batch["covisible"]))
    return metrics


def medium_eval_summary(learned: dict[str, Tensor], scene: SceneData) -> dict[str, float | None]:
    """`NAME_r|g|b` for each of `learned`'s 'b_inf', 'beta_d', 'beta_b' [3] and, where the scene knows its medium,
    `NAME_rel_error` = the largest relative error over the channels against it."""
    out: dict[str, float | None] = {}
    for name, value in learned.items():
        for channel, v in zip("rgb", value.tolist(), strict=True):
            out[f"{name}_{channel}"] = v
    if scene.gt is None or not scene.gt.medium or not learned:
        return out
    truths = dict(zip(("beta_d", "beta_b", "b_inf"), scene.gt.medium_tensors(), strict=True))
    for name in ("b_inf", "beta_d", "beta_b"):
        truth = truths[name]
        rel = (learned[name].cpu() - truth).abs() / truth.abs().clamp_min(1e-6)
        out[f"{name}_rel_error"] = float(rel.max())
    return out
