"""Geometry evaluation against a ground-truth point cloud: nearest distances and similarity alignment."""

from __future__ import annotations

import numpy as np
import torch
from torch import Tensor


def distance_to_ground_truth(points: Tensor, gt_points: Tensor, max_block: int = 2**24,
                             return_index: bool = False) -> Tensor | tuple[Tensor, Tensor]:
    """Distance [N] from each point [N, 3] to its nearest ground-truth point [M, 3] (same frame and units).

    Brute force over blocks of query points (at most `max_block` distances, 64 MB, at once; ground-truth
    vertices, not the mesh's faces: a coarse mesh overestimates distances): the nearest point is chosen with a
    float32 matrix product on coordinates centred at the ground truth's mean (no cancellation far from
    the origin), and its distance recomputed exactly in float64. Runs on the points' device; on a CPU,
    300k Gaussians against 1M ground-truth points take minutes (use a GPU for that size).
    """
    if points.ndim != 2 or points.shape[-1] != 3 or gt_points.ndim != 2 or gt_points.shape[-1] != 3:
        raise ValueError(f"expected points [N, 3] and gt_points [M, 3], got {tuple(points.shape)} and "
                         f"{tuple(gt_points.shape)}")
    if len(gt_points) == 0:
        raise ValueError("no ground-truth points")
    device = points.device
    gt64 = gt_points.to(device=device, dtype=torch.float64)
    centre = gt64.mean(dim=0)
    gt32 = (gt64 - centre).float()
    chunk = max(1, max_block // len(gt_points))
    distances = torch.empty(len(points), dtype=torch.float64, device=device)
    indices = torch.empty(len(points), dtype=torch.long, device=device)
    for start in range(0, len(points), chunk):
        query64 = points[start : start + chunk].to(torch.float64)
        d2 = torch.cdist((query64 - centre).float(), gt32, compute_mode="use_mm_for_euclid_dist")
        nearest = d2.argmin(dim=1)
        indices[start : start + chunk] = nearest
        distances[start : start + chunk] = (query64 - gt64[nearest]).norm(dim=-1)
    result = distances.to(points.dtype if points.is_floating_point() else torch.float32)
    return (result, indices) if return_index else result


def umeyama(source: np.ndarray, target: np.ndarray, with_scale: bool = True) -> tuple[float, np.ndarray, np.ndarray]:
    """Similarity (s, R, t) minimising sum |target - (s R source + t)|^2 over corresponding points [N, 3]
    (Umeyama 1991); needs N >= 3 points not on one line."""
    source, target = np.asarray(source, dtype=np.float64), np.asarray(target, dtype=np.float64)
    if source.shape != target.shape or source.ndim != 2 or source.shape[1] != 3 or len(source) < 3:
        raise ValueError(f"umeyama needs two [N, 3] arrays of corresponding points, N >= 3; got {source.shape} "
                         f"and {target.shape}")
    mu_s, mu_t = source.mean(axis=0), target.mean(axis=0)
    xs, xt = source - mu_s, target - mu_t
    cov = xt.T @ xs / len(source)
    U, D, Vt = np.linalg.svd(cov)
    S = np.eye(3)
    if np.linalg.det(U) * np.linalg.det(Vt) < 0:
        S[2, 2] = -1.0
    R = U @ S @ Vt
    var_s = (xs**2).sum() / len(source)
    if var_s <= 0 or np.linalg.matrix_rank(xs, tol=1e-9 * max(1.0, np.abs(xs).max())) < 2:
        raise ValueError("umeyama: the source points are (nearly) collinear or identical; the alignment is undefined")
    s = float((D * np.diag(S)).sum() / var_s) if with_scale else 1.0
    t = mu_t - s * R @ mu_s
    return s, R, t


def apply_similarity(points: np.ndarray, s: float, R: np.ndarray, t: np.ndarray) -> np.ndarray:
    """s R x + t for points [N, 3]."""
    return s * np.asarray(points) @ np.asarray(R).T + np.asarray(t)
