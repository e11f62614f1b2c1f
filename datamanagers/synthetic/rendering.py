"""Ray casting the seabed and forming the underwater image through the known medium (homogeneous or varying in
space)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from uw3dgs.datamanagers.synthetic.config import RAY_SAMPLES, SyntheticSceneConfig
from uw3dgs.datamanagers.synthetic.terrain import Terrain
from uw3dgs.datamanagers.synthetic.water_types import water_type

# Rendering


@dataclass
class RenderedView:
    """One view's ground truth and images."""

    c2w: np.ndarray
    centre_dirs: np.ndarray
    """[H, W, 3] unit world directions of the rays through the pixel centres."""
    ranges: np.ndarray
    """[H, W] range along the pixel-centre ray (metres), inf for open water."""
    clean: np.ndarray
    """[H, W, 3] uint8 clean radiance (0 for open water)."""
    underwater: np.ndarray
    """[H, W, 3] uint8 underwater image."""
    ray_mean: np.ndarray | None = None
    """[H, W] mean of the medium profile's factor along each pixel-centre ray to the seabed (the pixel's beta is
    the reference beta times it); None for a homogeneous medium."""


def ray_directions(K: np.ndarray, c2w: np.ndarray, u: np.ndarray, v: np.ndarray) -> np.ndarray:
    """Unit world directions [..., 3] of the rays through image points (u, v) in pixels, where the
    centre of the top-left pixel is (0.5, 0.5)."""
    cam = np.stack([(u - K[0, 2]) / K[0, 0], (v - K[1, 2]) / K[1, 1], np.ones_like(u)], axis=-1)
    world = cam @ c2w[:3, :3].T
    return world / np.linalg.norm(world, axis=-1, keepdims=True)


def pixel_rays(K: np.ndarray, c2w: np.ndarray, width: int, height: int, offsets: np.ndarray) -> np.ndarray:
    """Ray directions [S, H, W, 3] through every pixel's corner + offset, offsets [S, 2] in pixels."""
    v, u = np.meshgrid(np.arange(height, dtype=float), np.arange(width, dtype=float), indexing="ij")
    return ray_directions(K, c2w, u[None] + offsets[:, 0, None, None], v[None] + offsets[:, 1, None, None])


def underwater_image(clean: np.ndarray, ranges: np.ndarray, beta_D: np.ndarray, beta_B: np.ndarray, B_inf: np.ndarray,
                     ray_mean: np.ndarray | None = None) -> np.ndarray:
    """I = J exp(-beta_D m t) + B_inf (1 - exp(-beta_B m t)) at range t, m the mean of a varying medium's profile
    factor along the ray (`ray_mean`, same shape as `ranges`; None: 1, a homogeneous medium). exp(-beta_D m t) is the
    exact Beer-Lambert transmittance; the backscatter term is the method's ray-mean model, which is also the exact
    integral of a source B_inf beta_B(s) attenuated by beta_B on its way back (int_0^t beta_B(s) exp(-int_0^s
    beta_B) ds = 1 - exp(-int_0^t beta_B)). At t = inf (open water) the optical depth is infinite wherever beta > 0,
    so only B_inf remains (and J, which is 0 there, where beta = 0: clear water)."""
    finite = np.isfinite(ranges)
    t = np.where(finite, ranges, 0.0)
    path = (t if ray_mean is None else ray_mean * t)[..., None]

    def depth(beta: np.ndarray) -> np.ndarray:
        return np.where(finite[..., None], beta * path, np.where(beta > 0, np.inf, 0.0))

    return clean * np.exp(-depth(beta_D)) + B_inf * (1.0 - np.exp(-depth(beta_B)))


def profile_factor(cfg: SyntheticSceneConfig, points: np.ndarray) -> np.ndarray:
    """The medium profile's factor f [...] >= 1 at world points [..., 3] (beta = reference beta x f)."""
    gain = cfg.medium_profile_gain
    if cfg.medium_profile == "turbid-bottom":
        return 1.0 + gain * np.exp(-np.maximum(points[..., 2], 0.0) / cfg.turbid_height)
    if cfg.medium_profile == "gradient":
        angle = np.radians(cfg.gradient_azimuth_deg)
        along = (points[..., 0] - cfg.gradient_center[0]) * np.cos(angle) + \
            (points[..., 1] - cfg.gradient_center[1]) * np.sin(angle)
        return 1.0 + gain * 0.5 * (1.0 + np.tanh(along / cfg.gradient_length))
    if cfg.medium_profile == "plume":
        d2 = np.sum((points - np.asarray(cfg.plume_center, dtype=float)) ** 2, axis=-1)
        return 1.0 + gain * np.exp(-d2 / (2.0 * cfg.plume_radius ** 2))
    return np.ones(points.shape[:-1])


def beta_field(cfg: SyntheticSceneConfig, points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The true beta_D and beta_B [N, 3] (per metre) at world points [N, 3]: the reference medium
    (`medium_parameters`, the values in gt/medium.json) times the profile's factor, so a learned field can be scored
    against the truth anywhere."""
    medium = medium_parameters(cfg)
    f = profile_factor(cfg, np.asarray(points, dtype=float))[..., None]
    return medium["beta_D"] * f, medium["beta_B"] * f


def ray_mean_factor(cfg: SyntheticSceneConfig, origin: np.ndarray, dirs: np.ndarray, ranges: np.ndarray,
                    samples: int = RAY_SAMPLES, chunk: int = 4096) -> np.ndarray:
    """Mean of the profile's factor along each ray [...] from `origin` along unit `dirs` [..., 3] to `ranges` [...]
    (midpoint rule with `samples` points); rays of infinite range get NaN (their optical depth is infinite)."""
    flat_dirs, flat_t = dirs.reshape(-1, 3), ranges.reshape(-1)
    out = np.full(flat_t.shape, np.nan)
    s = (np.arange(samples) + 0.5) / samples
    for start in range(0, len(flat_t), chunk):
        t = flat_t[start:start + chunk]
        ok = np.isfinite(t)
        if ok.any():
            dist = t[ok, None] * s  # [P, S]
            points = origin + flat_dirs[start:start + chunk][ok, None, :] * dist[..., None]
            out[start:start + chunk][ok] = profile_factor(cfg, points).mean(axis=1)
    return out.reshape(ranges.shape)


def to_uint8(x: np.ndarray) -> np.ndarray:
    return np.round(np.clip(x, 0.0, 1.0) * 255.0).astype(np.uint8)


def render_view(
    cfg: SyntheticSceneConfig, terrain: Terrain, K: np.ndarray, c2w: np.ndarray, medium: dict[str, np.ndarray]
) -> RenderedView:
    """Ray-cast one view: range at the pixel centre, clean radiance averaged over s x s sub-rays,
    and the underwater image from the per-pixel formation model (exactly the model the method fits)."""
    s = cfg.supersample
    grid = (np.arange(s) + 0.5) / s
    offsets = np.array([(a, b) for b in grid for a in grid] + [(0.5, 0.5)])
    dirs = pixel_rays(K, c2w, cfg.width, cfg.height, offsets)
    origin = c2w[:3, 3]
    t = terrain.cast(origin, dirs.reshape(-1, 3), cfg.march_steps).reshape(dirs.shape[:-1])
    hit = np.isfinite(t)
    points = origin + dirs * np.where(hit, t, 0.0)[..., None]
    colours = terrain.radiance_at(points[..., 0].ravel(), points[..., 1].ravel()).reshape(dirs.shape)
    colours *= hit[..., None]
    count = hit[:s * s].sum(axis=0)[..., None]
    clean = np.where(count > 0, colours[:s * s].sum(axis=0) / np.maximum(count, 1), colours[-1])
    ranges = t[-1]
    clean8 = to_uint8(np.where(np.isfinite(ranges)[..., None], clean, 0.0))
    # The underwater image uses the stored 8-bit clean image, so gt/ reproduces it to 8-bit rounding.
    ray_mean = None if cfg.medium_profile == "homogeneous" else ray_mean_factor(cfg, origin, dirs[-1], ranges)
    uw = underwater_image(clean8 / 255.0, ranges, medium["beta_D"], medium["beta_B"], medium["B_inf"], ray_mean)
    return RenderedView(c2w, dirs[-1], ranges, clean8, to_uint8(uw), ray_mean)


def medium_parameters(cfg: SyntheticSceneConfig) -> dict[str, np.ndarray]:
    """The true (reference) medium: betas scaled by `medium_strength`, per metre; the water type's when one is set.
    With a medium profile these are the values where its factor is 1 (see `beta_field`)."""
    if cfg.water_type is not None:
        water = water_type(cfg.water_type)
        beta_D, beta_B, B_inf = water.beta_D, water.beta_B, cfg.water_light * np.array(water.B_inf)
    else:
        beta_D, beta_B, B_inf = cfg.beta_D, cfg.beta_B, cfg.B_inf
    return {
        "beta_D": cfg.medium_strength * np.array(beta_D),
        "beta_B": cfg.medium_strength * np.array(beta_B),
        "B_inf": np.array(B_inf),
    }
