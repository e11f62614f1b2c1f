"""SfM-like initial points: seabed points seen in the views, with their (underwater) colours."""

from __future__ import annotations

import numpy as np

from uw3dgs.datamanagers.synthetic.config import SyntheticSceneConfig
from uw3dgs.datamanagers.synthetic.rendering import RenderedView, ray_directions

# SfM-like points


def sample_points(
    cfg: SyntheticSceneConfig, views: list[RenderedView], K: np.ndarray, rng: np.random.Generator
) -> tuple[np.ndarray, np.ndarray]:
    """What SfM would give: noisy samples of the visible surface coloured by the underwater images,
    plus outliers scattered in the frusta. Returns xyz [P, 3] float64 and rgb [P, 3] uint8."""
    ranges = np.stack([v.ranges for v in views])
    finite = np.isfinite(ranges)
    scale = float(np.median(ranges[finite]))
    near, far = float(ranges[finite].min()), float(ranges[finite].max())
    n_out = int(round(cfg.num_points * cfg.outlier_fraction))
    candidates = np.flatnonzero(finite)
    picked = rng.choice(candidates, size=min(cfg.num_points - n_out, len(candidates)), replace=False)
    k, i, j = np.unravel_index(picked, ranges.shape)
    centres = np.stack([v.c2w[:3, 3] for v in views])
    dirs = np.stack([v.centre_dirs for v in views])
    surface = centres[k] + dirs[k, i, j] * ranges[k, i, j, None]
    surface += rng.normal(0.0, cfg.point_noise * scale, surface.shape)
    uw = np.stack([v.underwater for v in views])
    # Outliers: random depths along random rays of random views, coloured by the pixel they fall in.
    ko = rng.integers(len(views), size=n_out)
    u, v = rng.uniform(0.0, cfg.width, n_out), rng.uniform(0.0, cfg.height, n_out)
    out_dirs = np.array([ray_directions(K, views[a].c2w, b, c) for a, b, c in zip(ko, u, v, strict=True)])
    out_dirs = out_dirs.reshape(n_out, 3)
    io, jo = v.astype(int), u.astype(int)
    outliers = centres[ko] + out_dirs * rng.uniform(near, far, (n_out, 1))
    xyz = np.concatenate([surface, outliers])
    rgb = np.concatenate([uw[k, i, j], uw[ko, io, jo]])
    return xyz, rgb
