"""Marine snow: bright particles in the water column in front of the seabed, in the underwater images only."""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from uw3dgs.datamanagers.synthetic.config import SyntheticSceneConfig
from uw3dgs.datamanagers.synthetic.rendering import (
    RenderedView,
    ray_directions,
    ray_mean_factor,
    to_uint8,
    underwater_image,
)
from uw3dgs.datamanagers.synthetic.terrain import Terrain
from uw3dgs.datamanagers.synthetic.writers import image_names

# Marine snow


@dataclass
class MarineSnow:
    """The particles of one view (arrays of length P)."""

    uv: np.ndarray
    """[P, 2] image position of the centre, pixels (the top-left pixel's centre is (0.5, 0.5))."""
    xyz: np.ndarray
    """[P, 3] world position of the centre, metres."""
    range: np.ndarray
    """[P] distance from the camera centre, metres (always less than the seabed's along that ray)."""
    radius: np.ndarray
    """[P] radius in metres."""
    radius_px: np.ndarray
    """[P] apparent radius in pixels, radius f / range."""


def marine_snow_particles(cfg: SyntheticSceneConfig, terrain: Terrain, K: np.ndarray, c2w: np.ndarray,
                          rng: np.random.Generator) -> MarineSnow:
    """`cfg.marine_snow` particles for the view `c2w`: each on the ray of a random image point, at a random range
    between `marine_snow_range` and the seabed seen along that ray (closer where the seabed is nearer)."""
    n = cfg.marine_snow
    uv = rng.uniform(0.0, 1.0, (n, 2)) * np.array([cfg.width, cfg.height])
    q = rng.uniform(0.0, 1.0, n)
    radius = rng.uniform(*cfg.marine_snow_radius, n)
    dirs = ray_directions(K, c2w, uv[:, 0], uv[:, 1])
    surface = terrain.cast(c2w[:3, 3], dirs, cfg.march_steps)
    far = np.minimum(cfg.marine_snow_range[1], surface)
    near = np.minimum(cfg.marine_snow_range[0], 0.5 * far)
    ranges = near + q * (far - near)  # q < 1: strictly in front of the seabed
    xyz = c2w[:3, 3] + dirs * ranges[:, None]
    return MarineSnow(uv, xyz, ranges, radius, radius * K[0, 0] / ranges)


def add_marine_snow(cfg: SyntheticSceneConfig, view: RenderedView, snow: MarineSnow,
                    medium: dict[str, np.ndarray]) -> np.ndarray:
    """The view's underwater image (uint8) with its particles composited in, far to near: where a particle
    covers a share a of a pixel (4 x 4 sub-samples, antialiased) and is in front of that pixel's seabed,
    I = (1 - a) I + a I_p, with I_p = J exp(-beta_D z) + B_inf (1 - exp(-beta_B z)) the particle seen through z
    of water. Pixels no particle covers keep the bytes of `view.underwater`."""
    water = (medium["beta_D"], medium["beta_B"], medium["B_inf"])
    uw = underwater_image(view.clean / 255.0, view.ranges, *water, view.ray_mean)
    particle_mean = [None] * len(snow.range)
    if view.ray_mean is not None:  # a varying medium: each particle is seen through the mean beta along its own ray
        origin = view.c2w[:3, 3]
        particle_mean = ray_mean_factor(cfg, origin, (snow.xyz - origin) / snow.range[:, None], snow.range)
    sub = (np.arange(4) + 0.5) / 4
    for p in np.argsort(-snow.range):
        (u, v), r, z = snow.uv[p], snow.radius_px[p], snow.range[p]
        j0, j1 = max(int(u - r) - 1, 0), min(int(u + r) + 2, cfg.width)
        i0, i1 = max(int(v - r) - 1, 0), min(int(v + r) + 2, cfg.height)
        su = (np.arange(j0, j1)[:, None] + sub).ravel()  # sub-sample positions along x, then y
        sv = (np.arange(i0, i1)[:, None] + sub).ravel()
        dist = np.hypot(su[None, :] - u, sv[:, None] - v)
        inside = np.clip((r - dist) * 4 + 0.5, 0.0, 1.0)  # soft edge over one sub-sample
        cover = inside.reshape(i1 - i0, 4, j1 - j0, 4).mean(axis=(1, 3))
        cover *= view.ranges[i0:i1, j0:j1] > z  # the seabed in front hides it
        radiance = underwater_image(np.full(3, cfg.marine_snow_brightness), np.asarray(z), *water,
                                    None if particle_mean[p] is None else np.asarray(particle_mean[p]))
        a = cover[..., None]
        uw[i0:i1, j0:j1] = np.where(a > 0, (1.0 - a) * uw[i0:i1, j0:j1] + a * radiance, uw[i0:i1, j0:j1])
    return to_uint8(uw)


def write_marine_snow(path: Path, snows: list[MarineSnow]) -> None:
    """gt/marine_snow.json: every particle, with the view (image) it is drawn in."""
    particles = [
        {"image": name, "view": k, "uv": [float(x) for x in s.uv[p]], "xyz": [float(x) for x in s.xyz[p]],
         "range": float(s.range[p]), "radius": float(s.radius[p]), "radius_px": float(s.radius_px[p])}
        for k, (name, s) in enumerate(zip(image_names(len(snows)), snows, strict=True))
        for p in range(len(s.range))
    ]
    content = {"units": "metres; uv and radius_px in pixels (top-left pixel centre at (0.5, 0.5))",
               "particles": particles}
    path.write_text(json.dumps(content, indent=1) + "\n")
