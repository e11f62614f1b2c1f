"""The survey's cameras: intrinsics and poses along the chosen path, checked to see the seabed."""

from __future__ import annotations

from dataclasses import replace

import numpy as np

from uw3dgs.datamanagers.synthetic.config import SyntheticSceneConfig
from uw3dgs.datamanagers.synthetic.terrain import Terrain

# Cameras


def intrinsics(cfg: SyntheticSceneConfig) -> np.ndarray:
    """3x3 K with square pixels and the principal point at the image centre (COLMAP pixel convention:
    the centre of the top-left pixel is (0.5, 0.5))."""
    f = 0.5 * cfg.width / np.tan(0.5 * np.radians(cfg.fov_deg))
    return np.array([[f, 0.0, 0.5 * cfg.width], [0.0, f, 0.5 * cfg.height], [0.0, 0.0, 1.0]])


def _look_rotation(heading: float, tilt: float, roll: float) -> np.ndarray:
    """Camera-to-world rotation (columns: camera x right, y down, z forward) for a camera facing
    `heading` (radians from +x, counter-clockwise), its axis `tilt` radians from straight down."""
    h = np.array([np.cos(heading), np.sin(heading), 0.0])
    z = np.sin(tilt) * h + np.cos(tilt) * np.array([0.0, 0.0, -1.0])
    x = np.array([np.sin(heading), -np.cos(heading), 0.0])  # h x up: right of the heading
    y = np.cross(z, x)
    x, y = np.cos(roll) * x + np.sin(roll) * y, -np.sin(roll) * x + np.cos(roll) * y
    return np.stack([x, y, z], axis=1)


def _path(cfg: SyntheticSceneConfig) -> tuple[np.ndarray, np.ndarray]:
    """Nominal camera centres [N, 3] and headings [N] of the chosen path, centred on the origin; with
    `pass_altitudes`, one pass per altitude, each moved back along its headings to look at the same seabed."""
    if not cfg.pass_altitudes:
        return _one_pass(cfg)
    centres, headings = [], []
    for altitude, views in zip(cfg.pass_altitudes, np.array_split(np.arange(cfg.num_views), len(cfg.pass_altitudes)),
                               strict=True):
        c, h = _one_pass(replace(cfg, num_views=len(views), altitude=altitude, pass_altitudes=()))
        back = (altitude - cfg.altitude) * np.tan(np.radians(cfg.tilt_deg))
        c[:, :2] -= back * np.stack([np.cos(h), np.sin(h)], axis=1)
        centres.append(c)
        headings.append(h)
    return np.concatenate(centres), np.concatenate(headings)


def _one_pass(cfg: SyntheticSceneConfig) -> tuple[np.ndarray, np.ndarray]:
    """Nominal camera centres [N, 3] and headings [N] of the chosen path at `altitude`, centred on the origin."""
    n, half = cfg.num_views, 0.5 * cfg.path_length
    if cfg.path == "forward":
        s = np.linspace(-half, half, n)
        sway = 0.3 * np.sin(2 * np.pi * s / cfg.path_length)
        slope = 0.3 * 2 * np.pi / cfg.path_length * np.cos(2 * np.pi * s / cfg.path_length)
        return np.stack([sway, s, np.full(n, cfg.altitude)], axis=1), np.arctan2(1.0, slope)
    if cfg.path == "loop":
        angle = 2 * np.pi * np.arange(n) / n
        r = cfg.loop_radius
        centres = np.stack([r * np.cos(angle), r * np.sin(angle), np.full(n, cfg.altitude)], axis=1)
        return centres, angle + np.pi  # facing the centre
    centres, headings = [], []
    for line, idx in enumerate(np.array_split(np.arange(n), cfg.lawnmower_lines)):
        s = np.linspace(-half, half, len(idx)) * (1 if line % 2 == 0 else -1)
        y = (line - 0.5 * (cfg.lawnmower_lines - 1)) * cfg.line_spacing
        centres.append(np.stack([s, np.full(len(idx), y), np.full(len(idx), cfg.altitude)], axis=1))
        headings.append(np.full(len(idx), 0.0 if line % 2 == 0 else np.pi))
    return np.concatenate(centres), np.concatenate(headings)


def camera_poses(cfg: SyntheticSceneConfig, rng: np.random.Generator) -> np.ndarray:
    """Camera-to-world matrices [N, 4, 4] (OpenCV axes) along the path, with random jitter."""
    centres, headings = _path(cfg)
    n = len(centres)
    centres = centres + rng.normal(0.0, cfg.pose_jitter, (n, 3))
    jitter = np.radians(cfg.angle_jitter_deg) * rng.normal(size=(n, 3))
    c2w = np.tile(np.eye(4), (n, 1, 1))
    for k in range(n):
        tilt = np.radians(cfg.tilt_deg) + jitter[k, 1]
        c2w[k, :3, :3] = _look_rotation(headings[k] + jitter[k, 0], tilt, jitter[k, 2])
        c2w[k, :3, 3] = centres[k]
    return c2w


def focus_area(c2w: np.ndarray, margin: float = 2.0) -> np.ndarray:
    """(x_lo, x_hi, y_lo, y_hi) around where the optical axes meet the mean seabed: rocks go there."""
    axes, centres = c2w[:, :3, 2], c2w[:, :3, 3]
    reach = centres[:, 2] / np.maximum(-axes[:, 2], 0.2)  # horizontal-ish axes: stop a few altitudes out
    ground = centres + axes * reach[:, None]
    return np.array(
        [ground[:, 0].min() - margin, ground[:, 0].max() + margin,
         ground[:, 1].min() - margin, ground[:, 1].max() + margin]
    )


def check_cameras(terrain: Terrain, c2w: np.ndarray) -> None:
    """Every camera must float inside the terrain square, clear of the seabed."""
    lo, hi = terrain.extent
    centres = c2w[:, :3, 3]
    inside = (centres[:, :2] > lo).all(axis=1) & (centres[:, :2] < hi).all(axis=1)
    if not inside.all():
        raise ValueError(
            f"camera {int(np.argmin(inside))} lies outside the {hi - lo:.1f} m terrain square: "
            "increase terrain_size or shorten the path"
        )
    clearance = centres[:, 2] - terrain.height_at(centres[:, 0], centres[:, 1])
    if clearance.min() < 0.2:
        worst = int(np.argmin(clearance))
        raise ValueError(f"camera {worst} is {clearance[worst]:.2f} m above the seabed: increase altitude")
