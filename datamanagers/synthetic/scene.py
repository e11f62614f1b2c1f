"""The built-in synthetic underwater scene: a procedural seabed seen through water with a known medium.

No real dataset gives the clean radiance, the true ranges and the true medium; this scene does, so URI
quality, depth error and medium recovery can be measured. It is written in the SeaThru-NeRF layout
(`Images_wb/`, `sparse/0/`, `poses_bounds.npy`) plus `gt/`, so one reader serves real and synthetic data.

World frame: metres, z up, mean seabed at z = 0. Cameras follow OpenCV/COLMAP (x right, y down,
z forward). Every depth here is a range: the distance along the pixel's ray from the camera centre.
"""

from __future__ import annotations

import hashlib
import json
from dataclasses import asdict, dataclass, fields
from pathlib import Path
from typing import Literal

import numpy as np
import pycolmap
from PIL import Image
from rich.progress import Progress

from uw3dgs.datamanagers.synthetic.water_types import SOURCES as WATER_TYPE_SOURCES
from uw3dgs.datamanagers.synthetic.water_types import WATER_TYPES, WAVELENGTHS_NM, water_type
from uw3dgs.options import CheckedConfig, OptionError, check_number

GENERATOR_VERSION = 2
"""Bump when the generator's output changes for an unchanged config: it is part of `cache_key`."""

RGB = tuple[float, float, float]
WaterTypeName = Literal["I", "II", "III", "1C", "3C", "5C", "7C", "9C"]
MediumProfile = Literal["homogeneous", "turbid-bottom", "plume"]

RAY_SAMPLES = 128
"""Samples along each ray (midpoint rule) for the ray mean of a spatially varying medium."""


@dataclass(frozen=True)
class SyntheticSceneConfig(CheckedConfig):
    """Everything that defines a synthetic scene; the same config always gives the same bytes."""

    seed: int = 0
    """Seed of every random choice (terrain, texture, poses, points)."""
    num_views: int = 32
    """Number of cameras (images)."""
    width: int = 128
    """Image width in pixels."""
    height: int = 96
    """Image height in pixels."""
    fov_deg: float = 60.0
    """Horizontal field of view in degrees (pinhole, square pixels, principal point at the centre)."""
    path: Literal["forward", "lawnmower", "loop"] = "forward"
    """Camera path: a gently swaying forward pass (like SeaThru-NeRF captures), a lawnmower survey, or a loop
    around the scene centre looking inward (a diver circling a coral head: every view has neighbours on both
    sides, so no test view looks past the end of the path)."""
    altitude: float = 3.0
    """Camera height above the mean seabed, in metres."""
    tilt_deg: float = 55.0
    """Angle of the optical axis from straight down (0 = nadir); above ~50 the image top sees open water
    (as in forward-looking dives), which is where the veiling light B_inf shows on its own."""
    path_length: float = 6.0
    """Length of the forward pass, or of each lawnmower line, in metres."""
    lawnmower_lines: int = 3
    """Number of parallel lines of the lawnmower path (alternating direction)."""
    line_spacing: float = 1.5
    """Distance between lawnmower lines, in metres."""
    loop_radius: float = 3.0
    """Radius of the loop path, in metres."""
    pose_jitter: float = 0.05
    """Standard deviation of random camera position perturbations, in metres (a real diver wobbles)."""
    angle_jitter_deg: float = 2.0
    """Standard deviation of random yaw, tilt and roll perturbations, in degrees."""
    terrain_size: float = 24.0
    """Side of the square seabed centred on the origin, in metres; rays leaving it see open water."""
    open_water: bool = True
    """Whether rays that leave the seabed square see open water (I = B_inf). False continues the seabed beyond the
    square as its mirror image, so every ray pointing below the horizon meets the seabed (ranges then reach further)
    and the seabed inside the square is unchanged; a view with rays above the horizon is refused (lower tilt_deg)."""
    terrain_resolution: float = 0.02
    """Grid spacing of the height field and texture, in metres (finest texture detail is 2-3 cells)."""
    relief: float = 0.25
    """Standard deviation of the large-scale seabed height (dunes, hollows), in metres."""
    num_rocks: int = 8
    """Number of boulders placed in the area the cameras look at."""
    ripple_amplitude: float = 0.025
    """Amplitude of sand ripples, in metres."""
    ripple_wavelength: float = 0.3
    """Wavelength of sand ripples, in metres."""
    num_specks: int = 400
    """Small colourful objects (shells, starfish, sponges) scattered over the viewed area."""
    num_dark_patches: int = 60
    """Near-black patches (sea-urchin clusters, dark sponges, crevices) over the viewed area: where the clean
    radiance is ~0 an underwater pixel shows the backscatter alone, which is what makes beta_B readable."""
    dark_patch_radius: tuple[float, float] = (0.1, 0.3)
    """Range of the dark patches' radii, in metres."""
    dark_patch_albedo: float = 0.03
    """Albedo of the dark patches (all channels)."""
    sun_elevation_deg: float = 60.0
    """Elevation of the directional light above the horizon, in degrees."""
    sun_azimuth_deg: float = 30.0
    """Azimuth of the directional light, counter-clockwise from +x, in degrees."""
    ambient: float = 0.35
    """Share of ambient light in the baked Lambertian shading (the rest comes from the sun)."""
    supersample: int = 2
    """Rays per pixel along each axis (2 = 2x2) averaged for the clean radiance, against aliasing."""
    march_steps: int = 64
    """Ray-marching samples per ray between the top and bottom of the terrain, before bisection."""
    beta_D: RGB = (0.40, 0.20, 0.12)
    """Direct-signal attenuation coefficients (R, G, B) per metre; red attenuates most."""
    beta_B: RGB = (0.30, 0.25, 0.20)
    """Backscatter coefficients (R, G, B) per metre."""
    B_inf: RGB = (0.05, 0.25, 0.35)
    """Veiling light (backscatter at infinite range), RGB in [0, 1]."""
    medium_strength: float = 1.0
    """Multiplier on both beta_D and beta_B (0 = clear water)."""
    water_type: WaterTypeName | None = None
    """A Jerlov water type (oceanic I, II, III; coastal 1C, 3C, 5C, 7C, 9C) whose published coefficients replace
    beta_D, beta_B and B_inf (leave those at their defaults): beta_D = beta_B = K_d (Jerlov 1976, Table XXVII) and
    B_inf = water_light x b / (a + b) (Solonenko & Mobley 2015), read at 600, 525, 475 nm for R, G, B
    (datamanagers/synthetic/water_types.py). None keeps the hand-set medium above."""
    water_light: float = 1.0
    """With water_type: the level E of the light in the water, B_inf = E b / (a + b) (Akkaynak & Treibitz 2018);
    1 = the white light of level 1 that lights the seabed's clean radiance (white-balanced images)."""
    medium_profile: MediumProfile = "homogeneous"
    """How beta_D and beta_B vary in space: both are the reference medium (above, or the water type's) times a
    factor f(x) >= 1. 'homogeneous': f = 1. 'turbid-bottom': f = 1 + gain exp(-max(z, 0) / turbid_height), z the
    height above the mean seabed (turbidity grows towards the seabed). 'plume': f = 1 + gain exp(-|x -
    plume_center|^2 / (2 plume_radius^2)), a Gaussian cloud. A pixel sees the mean of beta along its ray from the
    camera to the seabed (the method's model); B_inf stays one colour."""
    medium_profile_gain: float = 3.0
    """gain of medium_profile: beta at the seabed (turbid-bottom) or the plume's centre is (1 + gain) x reference."""
    turbid_height: float = 1.0
    """turbid-bottom: height above the mean seabed over which the extra turbidity falls by e, in metres."""
    plume_radius: float = 2.0
    """plume: standard deviation of the Gaussian cloud, in metres."""
    plume_center: tuple[float, float, float] = (0.0, 4.0, 1.0)
    """plume: centre (x, y, z) in metres (the default is where the forward path's cameras look)."""
    num_points: int = 4000
    """Number of SfM-like initial points written to points3D.bin (outliers included)."""
    point_noise: float = 0.01
    """Standard deviation of the points' position noise, as a fraction of the median range of all pixels."""
    outlier_fraction: float = 0.05
    """Share of points that are outliers scattered in the camera frusta between the near and far range."""
    marine_snow: int = 0
    """Marine snow: transient particles per view (0 = none, the default). Each is a small bright disc drawn into
    one underwater image only (Images_wb/), like a suspended particle lit by the strobe for one frame: a method
    that trusts every view grows floaters for them. Clean images, ranges, the medium and the SfM points stay
    those of the snow-free scene; the particles are listed in gt/marine_snow.json. Drawn from their own random
    stream: the rest of the scene is the same with or without snow."""
    marine_snow_range: tuple[float, float] = (0.75, 3.0)
    """Range of the particles' distances from the camera, in metres (a strobe lights the water near the camera);
    a particle is always in front of the seabed seen through its pixel (the far end stops there)."""
    marine_snow_radius: tuple[float, float] = (0.015, 0.03)
    """Range of the particles' radii, in metres. The apparent radius is r f / range pixels (f the focal length
    in pixels, 111 at the default 128 px width: 1-9 px across with the default ranges, 2.6 px typically)."""
    marine_snow_brightness: float = 1.0
    """Clean radiance J of a particle (grey, all channels; 1 = white), seen through the water between it and
    the camera like any object: J exp(-beta_D z) + B_inf (1 - exp(-beta_B z)) at its range z."""

    def check_options(self) -> None:
        """Reject settings the generator cannot honour, naming the knob (they usually come from flags)."""
        check_number(self, "seed", ge=0, integer=True)
        for name in ("num_views", "width", "height", "supersample", "lawnmower_lines", "num_points"):
            check_number(self, name, ge=1, integer=True)
        for name in ("num_rocks", "num_specks", "num_dark_patches"):
            check_number(self, name, ge=0, integer=True)
        check_number(self, "march_steps", ge=2, integer=True)
        for name in ("terrain_size", "terrain_resolution", "ripple_wavelength", "altitude", "loop_radius"):
            check_number(self, name, gt=0)
        for name in ("path_length", "line_spacing", "pose_jitter", "angle_jitter_deg", "relief", "ripple_amplitude",
                     "point_noise", "medium_strength"):
            check_number(self, name, ge=0)
        check_number(self, "fov_deg", gt=0, lt=180)
        check_number(self, "tilt_deg", ge=0, le=90)
        check_number(self, "sun_elevation_deg", gt=0, le=90)
        check_number(self, "sun_azimuth_deg")
        for name in ("ambient", "dark_patch_albedo", "outlier_fraction"):
            check_number(self, name, ge=0, le=1)
        for name in ("beta_D", "beta_B"):
            check_number(self, name, ge=0, each=True)
        check_number(self, "B_inf", ge=0, le=1, each=True)
        check_number(self, "dark_patch_radius", gt=0, each=True)
        if self.dark_patch_radius[0] > self.dark_patch_radius[1]:
            raise OptionError("dark_patch_radius", f"must be (smallest, largest), got {self.dark_patch_radius}")
        check_number(self, "marine_snow", ge=0, integer=True)
        for name in ("marine_snow_range", "marine_snow_radius"):
            check_number(self, name, gt=0, each=True)
            low, high = getattr(self, name)
            if low > high:
                raise OptionError(name, f"must be (smallest, largest), got {(low, high)}")
        check_number(self, "marine_snow_brightness", ge=0, le=1)
        check_number(self, "water_light", ge=0, le=1)
        if self.water_type is None and self.water_light != 1.0:
            raise OptionError("water_light", "only applies with water_type (the hand-set B_inf is used as it is)")
        if self.water_type is not None:
            if self.water_type not in WATER_TYPES:
                raise OptionError("water_type", f"must be one of {', '.join(WATER_TYPES)} (or None), "
                                                f"got {self.water_type!r}")
            defaults = {f.name: f.default for f in fields(self)}
            for name in ("beta_D", "beta_B", "B_inf"):
                if tuple(getattr(self, name)) != defaults[name]:
                    raise OptionError(name, f"cannot be set together with water_type (the water type "
                                            f"{self.water_type} sets beta_D, beta_B and B_inf)")
        if self.medium_profile not in ("homogeneous", "turbid-bottom", "plume"):
            raise OptionError("medium_profile", "must be one of homogeneous, turbid-bottom, plume, "
                                                f"got {self.medium_profile!r}")
        check_number(self, "medium_profile_gain", ge=0)
        for name in ("turbid_height", "plume_radius"):
            check_number(self, name, gt=0)
        check_number(self, "plume_center", each=True)


def _config_record(config: SyntheticSceneConfig) -> dict:
    """The config as written to gt/medium.json and hashed by `cache_key`. Knobs of an option that is off change
    nothing and are left out (marine snow, water type, open water, medium profile), so scenes without the option
    keep the keys and bytes they had before it existed."""
    record = asdict(config)
    unused = []
    if config.marine_snow == 0:
        unused += ["marine_snow", "marine_snow_range", "marine_snow_radius", "marine_snow_brightness"]
    if config.water_type is None:
        unused += ["water_type", "water_light"]
    if config.open_water:
        unused.append("open_water")
    if config.medium_profile != "turbid-bottom":
        unused.append("turbid_height")
    if config.medium_profile != "plume":
        unused += ["plume_radius", "plume_center"]
    if config.medium_profile == "homogeneous":
        unused += ["medium_profile", "medium_profile_gain"]
    for name in unused:
        del record[name]
    return record


def cache_key(config: SyntheticSceneConfig) -> str:
    """A short stable hash of the config and the generator version, to name a cache folder."""
    payload = json.dumps({"version": GENERATOR_VERSION, "config": _config_record(config)}, sort_keys=True)
    return hashlib.sha256(payload.encode()).hexdigest()[:12]


# ----------------------------------------------------------------------------------------------------
# Procedural terrain


def _smoothstep(lo: float, hi: float, x: np.ndarray) -> np.ndarray:
    t = np.clip((x - lo) / (hi - lo), 0.0, 1.0)
    return t * t * (3.0 - 2.0 * t)


def _lerp(a: np.ndarray, b: np.ndarray, t: np.ndarray) -> np.ndarray:
    return a + (b - a) * t


def _reflect(f: np.ndarray, m: float) -> np.ndarray:
    """Grid coordinate f folded into [0, m] by mirroring at 0 and m (a triangle wave of period 2m)."""
    g = np.mod(f, 2.0 * m)
    return np.where(g > m, 2.0 * m - g, g)


class _Noise:
    """Value noise on the terrain grid: random lattices interpolated separably (fast for a regular grid)."""

    def __init__(self, coords: np.ndarray, rng: np.random.Generator):
        self.coords = coords - coords[0]
        self.rng = rng

    def _layer(self, wavelength: float) -> np.ndarray:
        f = self.coords / wavelength + self.rng.uniform(0.0, 1.0, 2)[:, None]
        cells = np.floor(f).astype(np.int64)
        w = f - cells
        w = w * w * w * (w * (w * 6.0 - 15.0) + 10.0)  # quintic fade: smooth first and second derivatives
        lattice = self.rng.uniform(-1.0, 1.0, (cells[1].max() + 2, cells[0].max() + 2))
        (ix, iy), wx, wy = cells, w[0], w[1][:, None]
        rows = lattice[:, ix] * (1.0 - wx) + lattice[:, ix + 1] * wx  # interpolate along x, then y
        return rows[iy] * (1.0 - wy) + rows[iy + 1] * wy

    def fbm(self, wavelength: float, octaves: int) -> np.ndarray:
        """Fractal noise (octaves halve the wavelength and the amplitude), standardised to mean 0, std 1."""
        total = sum(0.5**o * self._layer(wavelength / 2**o) for o in range(octaves))
        return ((total - total.mean()) / total.std()).astype(np.float32)  # float32 halves the memory


@dataclass
class Terrain:
    """The seabed as a regular grid: heights for ray casting and baked shaded radiance for colour."""

    x0: float
    resolution: float
    heights: np.ndarray
    """[n, n] heights in metres; row i is y = x0 + i * resolution, column j is x = x0 + j * resolution."""
    radiance: np.ndarray
    """[n, n, 3] clean radiance (albedo times Lambertian shading) in [0, 1]."""
    mirror: bool = False
    """False: the seabed ends at the square's edge (rays beyond see open water). True: it continues beyond as its
    mirror image across each edge (an unbounded, continuous height field: every downward ray meets it)."""

    @property
    def extent(self) -> tuple[float, float]:
        return self.x0, self.x0 + (self.heights.shape[0] - 1) * self.resolution

    def _cell(self, x: np.ndarray, y: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Flat index of the grid cell holding each point (clamped to the grid, or folded into it with `mirror`)
        and the weights in it."""
        n = self.heights.shape[0]
        if self.mirror:
            fx = _reflect((x - self.x0) / self.resolution, n - 1.0)
            fy = _reflect((y - self.x0) / self.resolution, n - 1.0)
        else:
            fx = np.clip((x - self.x0) / self.resolution, 0.0, n - 1.0)
            fy = np.clip((y - self.x0) / self.resolution, 0.0, n - 1.0)
        j = np.minimum(fx.astype(np.int64), n - 2)
        i = np.minimum(fy.astype(np.int64), n - 2)
        return i * n + j, fx - j, fy - i

    def _bilinear(self, flat: np.ndarray, x: np.ndarray, y: np.ndarray) -> np.ndarray:
        n = self.heights.shape[0]
        idx, wx, wy = self._cell(x, y)
        if flat.ndim == 2:
            wx, wy = wx[..., None], wy[..., None]
        bottom = flat[idx] * (1.0 - wx) + flat[idx + 1] * wx
        top = flat[idx + n] * (1.0 - wx) + flat[idx + n + 1] * wx
        return bottom * (1.0 - wy) + top * wy

    def height_at(self, x: np.ndarray, y: np.ndarray) -> np.ndarray:
        return self._bilinear(self.heights.reshape(-1), x, y)

    def radiance_at(self, x: np.ndarray, y: np.ndarray) -> np.ndarray:
        return self._bilinear(self.radiance.reshape(-1, 3), x, y)

    def cast(self, origin: np.ndarray, dirs: np.ndarray, steps: int, chunk: int = 16384) -> np.ndarray:
        """Range to the first seabed hit of each unit ray [P, 3] from `origin`; inf for open water."""
        out = np.full(len(dirs), np.inf)
        for start in range(0, len(dirs), chunk):
            out[start : start + chunk] = self._cast_chunk(origin, dirs[start : start + chunk], steps)
        return out

    def _segment(self, origin: np.ndarray, dirs: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Where each ray can meet the seabed: between the planes of the highest and lowest point,
        and inside the terrain square."""
        h = self.heights
        lo, hi = self.extent
        down = dirs[:, 2] < -1e-12
        dz = np.where(down, -dirs[:, 2], 1.0)
        t0 = np.where(down, np.maximum((origin[2] - h.max()) / dz, 0.0), np.inf)
        t1 = np.where(down, (origin[2] - h.min()) / dz, -np.inf)
        if self.mirror:  # the seabed goes on beyond the square
            return t0, t1
        for axis in (0, 1):
            d = dirs[:, axis]
            safe = np.where(d == 0.0, 1.0, d)
            bound = np.where(d > 0, hi, lo)
            t1 = np.minimum(t1, np.where(d == 0.0, np.inf, (bound - origin[axis]) / safe))
        return t0, t1

    def _cast_chunk(self, origin: np.ndarray, dirs: np.ndarray, steps: int) -> np.ndarray:
        t0, t1 = self._segment(origin, dirs)
        out = np.full(len(dirs), np.inf)
        rays = np.nonzero(t1 > t0)[0]
        d, t0, t1 = dirs[rays], t0[rays], t1[rays]

        def above(t: np.ndarray, d: np.ndarray) -> np.ndarray:
            """Height of the ray point above the seabed (<= 0 once the ray has hit)."""
            x, y = origin[0] + d[..., 0] * t, origin[1] + d[..., 1] * t
            return origin[2] + d[..., 2] * t - self.height_at(x, y)

        # March uniformly, find the first sample below the surface, then bisect its bracket.
        ts = t0[:, None] + (t1 - t0)[:, None] * np.linspace(0.0, 1.0, steps)
        below = above(ts, d[:, None, :]) <= 0.0
        hit = below.any(axis=1)
        first = below.argmax(axis=1)[hit]
        rows = np.nonzero(hit)[0]
        lo_t, hi_t = ts[rows, np.maximum(first - 1, 0)], ts[rows, first]
        d = d[rows]
        for _ in range(16):
            mid = 0.5 * (lo_t + hi_t)
            inside = above(mid, d) <= 0.0
            hi_t = np.where(inside, mid, hi_t)
            lo_t = np.where(inside, lo_t, mid)
        out[rays[rows]] = 0.5 * (lo_t + hi_t)
        return out


# Albedo palettes (RGB); the texture is computed in float32 to keep the 1200 x 1200 x 3 grids light.
_SAND = np.array([[0.82, 0.75, 0.60], [0.60, 0.53, 0.42]], dtype=np.float32)
_ALGAE = np.array([[0.18, 0.42, 0.14], [0.42, 0.36, 0.12]], dtype=np.float32)
_ROCKS = np.array([[0.45, 0.43, 0.41], [0.52, 0.46, 0.38], [0.36, 0.35, 0.34], [0.58, 0.52, 0.46]],
                  dtype=np.float32)
_ENCRUSTING = np.array([[0.55, 0.28, 0.62], [0.88, 0.36, 0.48], [0.95, 0.55, 0.20]], dtype=np.float32)
_SPECKS = np.array(
    [[0.85, 0.22, 0.18], [0.95, 0.55, 0.20], [0.95, 0.85, 0.30], [0.93, 0.92, 0.88], [0.55, 0.28, 0.62]],
    dtype=np.float32,
)


def _window(coords: np.ndarray, cx: float, cy: float, radius: float) -> tuple[slice, slice]:
    """Grid slices (rows, columns) covering a square of half-side `radius` around (cx, cy)."""
    res = coords[1] - coords[0]
    j0, j1 = np.searchsorted(coords, [cx - radius, cx + radius + res])
    i0, i1 = np.searchsorted(coords, [cy - radius, cy + radius + res])
    return slice(i0, i1), slice(j0, j1)


def _rocks(
    cfg: SyntheticSceneConfig, coords: np.ndarray, noise: _Noise, focus: np.ndarray, rng: np.random.Generator
) -> tuple[np.ndarray, np.ndarray]:
    """Lumpy half-buried boulders inside `focus` (x_lo, x_hi, y_lo, y_hi): heights and colours."""
    n = len(coords)
    heights = np.zeros((n, n), dtype=np.float32)
    colours = np.zeros((n, n, 3), dtype=np.float32)
    lumps = 1.0 + 0.25 * np.clip(noise.fbm(0.6, 2), -2.0, 2.0)  # irregular outlines, no islands
    bumps = 1.0 + 0.08 * noise.fbm(0.1, 2)  # surface roughness
    for _ in range(cfg.num_rocks):
        cx, cy = rng.uniform(focus[0], focus[1]), rng.uniform(focus[2], focus[3])
        rx, ry = rng.uniform(0.35, 0.9, 2)
        angle = rng.uniform(0.0, np.pi)
        top = rng.uniform(0.5, 0.9) * min(rx, ry)
        colour = _ROCKS[rng.integers(len(_ROCKS))] * rng.uniform(0.9, 1.1, 3)
        rows, cols = _window(coords, cx, cy, 2.0 * max(rx, ry))
        x, y = coords[cols][None, :] - cx, coords[rows][:, None] - cy
        u, v = x * np.cos(angle) + y * np.sin(angle), -x * np.sin(angle) + y * np.cos(angle)
        s2 = ((u / rx) ** 2 + (v / ry) ** 2) * lumps[rows, cols]
        dome = top * np.clip(1.0 - s2, 0.0, 1.0) ** 0.6 * bumps[rows, cols]
        higher = dome > heights[rows, cols]
        heights[rows, cols] = np.where(higher, dome, heights[rows, cols])
        colours[rows, cols] = np.where(higher[..., None], colour, colours[rows, cols])
    return heights, colours


def _specks(
    cfg: SyntheticSceneConfig,
    coords: np.ndarray,
    albedo: np.ndarray,
    focus: np.ndarray,
    rng: np.random.Generator,
) -> None:
    """Paint small bright discs (shells, starfish, sponges) into `albedo`, antialiased on the grid."""
    res = coords[1] - coords[0]
    for _ in range(cfg.num_specks):
        cx, cy = rng.uniform(focus[0] - 2.0, focus[1] + 2.0), rng.uniform(focus[2] - 2.0, focus[3] + 2.0)
        radius = rng.uniform(0.03, 0.08)
        colour = _SPECKS[rng.integers(len(_SPECKS))] * rng.uniform(0.85, 1.0)
        rows, cols = _window(coords, cx, cy, radius + res)
        dist = np.hypot(coords[cols][None, :] - cx, coords[rows][:, None] - cy)
        cover = np.clip((radius - dist) / res + 0.5, 0.0, 1.0)[..., None]
        albedo[rows, cols] = _lerp(albedo[rows, cols], colour, cover)


def _dark_patches(cfg: SyntheticSceneConfig, coords: np.ndarray, noise: _Noise, albedo: np.ndarray,
                  focus: np.ndarray, rng: np.random.Generator) -> None:
    """Paint near-black patches with ragged outlines into `albedo` (on sand, algae and rocks alike)."""
    res = coords[1] - coords[0]
    ragged = 1.0 + 0.3 * np.clip(noise.fbm(0.15, 2), -2.0, 2.0)
    dark = np.full(3, cfg.dark_patch_albedo, dtype=np.float32)
    for _ in range(cfg.num_dark_patches):
        cx, cy = rng.uniform(focus[0] - 2.0, focus[1] + 2.0), rng.uniform(focus[2] - 2.0, focus[3] + 2.0)
        radius = rng.uniform(*cfg.dark_patch_radius)
        rows, cols = _window(coords, cx, cy, 1.6 * radius + res)
        dist = np.hypot(coords[cols][None, :] - cx, coords[rows][:, None] - cy) * ragged[rows, cols]
        cover = np.clip((radius - dist) / res + 0.5, 0.0, 1.0)[..., None]
        albedo[rows, cols] = _lerp(albedo[rows, cols], dark, cover)


def _albedo(
    cfg: SyntheticSceneConfig,
    coords: np.ndarray,
    noise: _Noise,
    algae: np.ndarray,
    rock: np.ndarray,
    rock_colours: np.ndarray,
    focus: np.ndarray,
    rng: np.random.Generator,
) -> np.ndarray:
    """Sand with grain, ragged algae patches, specks, and mottled rocks with colourful encrusting life."""
    sand_mix = _smoothstep(-1.5, 1.5, noise.fbm(1.2, 3))[..., None]
    sand = _lerp(*_SAND, sand_mix) * (1.0 + 0.12 * noise.fbm(0.06, 2))[..., None]
    algae_tone = _smoothstep(-1.0, 1.0, noise.fbm(0.7, 3))[..., None]
    algae_colour = _lerp(*_ALGAE, algae_tone) * (0.8 + 0.2 * np.tanh(noise.fbm(0.08, 2)))[..., None]
    ragged = algae * _smoothstep(-1.2, 0.2, noise.fbm(0.1, 2))
    albedo = _lerp(sand, algae_colour, ragged[..., None])
    _specks(cfg, coords, albedo, focus, rng)
    hue = _smoothstep(-0.6, 0.6, noise.fbm(0.5, 2))[..., None]
    encrusting = np.where(hue < 0.5, _lerp(_ENCRUSTING[0], _ENCRUSTING[1], 2 * hue),
                          _lerp(_ENCRUSTING[1], _ENCRUSTING[2], 2 * hue - 1))
    crust = _smoothstep(0.4, 1.2, noise.fbm(0.3, 3))[..., None]
    rock_albedo = _lerp(rock_colours * (1.0 + 0.15 * noise.fbm(0.1, 2))[..., None], encrusting, crust)
    albedo = _lerp(albedo, rock_albedo, rock[..., None])
    _dark_patches(cfg, coords, noise, albedo, focus, rng)
    return np.clip(albedo, 0.0, 1.0)


def _shading(cfg: SyntheticSceneConfig, heights: np.ndarray) -> np.ndarray:
    """Lambertian shading from a directional sun plus ambient light, baked per grid cell."""
    dh_dy, dh_dx = np.gradient(heights, cfg.terrain_resolution)
    normals = np.stack([-dh_dx, -dh_dy, np.ones_like(heights)], axis=-1)
    normals /= np.linalg.norm(normals, axis=-1, keepdims=True)
    el, az = np.radians(cfg.sun_elevation_deg), np.radians(cfg.sun_azimuth_deg)
    sun = np.array([np.cos(el) * np.cos(az), np.cos(el) * np.sin(az), np.sin(el)])
    return cfg.ambient + (1.0 - cfg.ambient) * np.clip(normals @ sun, 0.0, None)


def build_terrain(cfg: SyntheticSceneConfig, focus: np.ndarray, rng: np.random.Generator) -> Terrain:
    """Height field (dunes + boulders + ripples) and its baked clean radiance; rocks and specks go in
    `focus` (x_lo, x_hi, y_lo, y_hi), the area the cameras look at."""
    n = int(round(cfg.terrain_size / cfg.terrain_resolution)) + 1
    coords = -0.5 * cfg.terrain_size + np.arange(n) * cfg.terrain_resolution
    noise = _Noise(coords, rng)
    base = cfg.relief * noise.fbm(6.0, 4)
    algae = _smoothstep(0.4, 1.0, noise.fbm(2.5, 4))
    rock_heights, rock_colours = _rocks(cfg, coords, noise, focus, rng)
    rock = np.clip(rock_heights / 0.02, 0.0, 1.0)
    # Ripples: crests across a fixed direction, bent by low-frequency noise, flattened by algae and rocks.
    phase = 2 * np.pi * (coords[None, :] * 0.8 + coords[:, None] * 0.6) / cfg.ripple_wavelength
    ripples = cfg.ripple_amplitude * np.sin(phase + 2.5 * noise.fbm(1.5, 2))
    heights = base + rock_heights + ripples * (1.0 - 0.7 * algae) * (1.0 - rock)
    albedo = _albedo(cfg, coords, noise, algae, rock, rock_colours, focus, rng)
    radiance = np.clip(albedo * _shading(cfg, heights)[..., None], 0.0, 1.0)
    return Terrain(float(coords[0]), cfg.terrain_resolution, heights, radiance.astype(np.float32),
                   mirror=not cfg.open_water)


# ----------------------------------------------------------------------------------------------------
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
    """Nominal camera centres [N, 3] and headings [N] of the chosen path, centred on the origin."""
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


def _focus_area(c2w: np.ndarray, margin: float = 2.0) -> np.ndarray:
    """(x_lo, x_hi, y_lo, y_hi) around where the optical axes meet the mean seabed: rocks go there."""
    axes, centres = c2w[:, :3, 2], c2w[:, :3, 3]
    reach = centres[:, 2] / np.maximum(-axes[:, 2], 0.2)  # horizontal-ish axes: stop a few altitudes out
    ground = centres + axes * reach[:, None]
    return np.array(
        [ground[:, 0].min() - margin, ground[:, 0].max() + margin,
         ground[:, 1].min() - margin, ground[:, 1].max() + margin]
    )


def _check_cameras(terrain: Terrain, c2w: np.ndarray) -> None:
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


# ----------------------------------------------------------------------------------------------------
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


def _to_uint8(x: np.ndarray) -> np.ndarray:
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
    clean8 = _to_uint8(np.where(np.isfinite(ranges)[..., None], clean, 0.0))
    # The underwater image uses the stored 8-bit clean image, so gt/ reproduces it to 8-bit rounding.
    ray_mean = None if cfg.medium_profile == "homogeneous" else ray_mean_factor(cfg, origin, dirs[-1], ranges)
    uw = underwater_image(clean8 / 255.0, ranges, medium["beta_D"], medium["beta_B"], medium["B_inf"], ray_mean)
    return RenderedView(c2w, dirs[-1], ranges, clean8, _to_uint8(uw), ray_mean)


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


# ----------------------------------------------------------------------------------------------------
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
    return _to_uint8(uw)


def _write_marine_snow(path: Path, snows: list[MarineSnow]) -> None:
    """gt/marine_snow.json: every particle, with the view (image) it is drawn in."""
    particles = [
        {"image": name, "view": k, "uv": [float(x) for x in s.uv[p]], "xyz": [float(x) for x in s.xyz[p]],
         "range": float(s.range[p]), "radius": float(s.radius[p]), "radius_px": float(s.radius_px[p])}
        for k, (name, s) in enumerate(zip(_image_names(len(snows)), snows, strict=True))
        for p in range(len(s.range))
    ]
    content = {"units": "metres; uv and radius_px in pixels (top-left pixel centre at (0.5, 0.5))",
               "particles": particles}
    path.write_text(json.dumps(content, indent=1) + "\n")


# ----------------------------------------------------------------------------------------------------
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


# ----------------------------------------------------------------------------------------------------
# Writing the SeaThru-NeRF layout


def _image_names(n: int) -> list[str]:
    return [f"{k:04d}.png" for k in range(n)]


def write_colmap_model(sparse_dir: Path, K: np.ndarray, cfg: SyntheticSceneConfig, c2w: np.ndarray,
                       xyz: np.ndarray, rgb: np.ndarray) -> None:
    """cameras.bin (one PINHOLE camera), images.bin (world-to-camera poses), points3D.bin (empty tracks)."""
    rec = pycolmap.Reconstruction()
    params = [K[0, 0], K[1, 1], K[0, 2], K[1, 2]]
    rec.add_camera_with_trivial_rig(
        pycolmap.Camera(model="PINHOLE", width=cfg.width, height=cfg.height, params=params, camera_id=1)
    )
    for k, name in enumerate(_image_names(len(c2w))):
        w2c = np.linalg.inv(c2w[k])
        pose = pycolmap.Rigid3d(pycolmap.Rotation3d(w2c[:3, :3]), w2c[:3, 3])
        rec.add_image_with_trivial_frame(pycolmap.Image(name=name, camera_id=1, image_id=k + 1), pose)
    for p, c in zip(xyz, rgb, strict=True):
        rec.add_point3D(p, pycolmap.Track(), c)
    sparse_dir.mkdir(parents=True, exist_ok=True)
    rec.write_binary(str(sparse_dir))
    # COLMAP >= 3.12 adds rigs.bin and frames.bin; the dataset ships the classic three files only, and
    # readers (pycolmap included) rebuild trivial rigs without them.
    for extra in ("rigs.bin", "frames.bin"):
        (sparse_dir / extra).unlink(missing_ok=True)


def llff_poses_bounds(c2w: np.ndarray, K: np.ndarray, cfg: SyntheticSceneConfig,
                      z_bounds: np.ndarray) -> np.ndarray:
    """LLFF rows [N, 17]: the 3x5 matrix [R | t | (h, w, f)] of camera-to-world in LLFF axis order
    (down, right, back), flattened row-major, then the near and far z-depth bounds."""
    rows = []
    hwf = np.array([cfg.height, cfg.width, K[0, 0]], dtype=float)
    for pose, bounds in zip(c2w, z_bounds, strict=True):
        r = pose[:3, :3]
        llff = np.column_stack([r[:, 1], r[:, 0], -r[:, 2], pose[:3, 3], hwf])
        rows.append(np.concatenate([llff.ravel(), bounds]))
    return np.stack(rows)


def _z_bounds(view: RenderedView, index: int) -> np.ndarray:
    """Near and far camera z-depth of the visible seabed, as LLFF stores them."""
    z = view.ranges * (view.centre_dirs @ view.c2w[:3, 2])
    z = z[np.isfinite(z)]
    if z.size == 0:
        raise ValueError(f"view {index} sees no seabed: lower tilt_deg or altitude")
    return np.array([z.min(), z.max()])


def _write_png(path: Path, pixels: np.ndarray) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    Image.fromarray(pixels).save(path)


def _write_views(out_dir: Path, views: list[RenderedView]) -> None:
    for name, view in zip(_image_names(len(views)), views, strict=True):
        _write_png(out_dir / "Images_wb" / name, view.underwater)
        _write_png(out_dir / "gt" / "clean" / name, view.clean)
        range_path = out_dir / "gt" / "range" / Path(name).with_suffix(".npy")
        range_path.parent.mkdir(parents=True, exist_ok=True)
        np.save(range_path, view.ranges.astype(np.float32))


def _write_medium(path: Path, cfg: SyntheticSceneConfig, medium: dict[str, np.ndarray]) -> None:
    """gt/medium.json: beta_D, beta_B, B_inf (the homogeneous medium, or a varying one's reference values), units,
    seed, generator version and config; with a water type its name and sources, with a medium profile its formula
    and parameters (`beta_field` evaluates it)."""
    content = {key: [float(x) for x in value] for key, value in medium.items()}
    content |= {"units": "per metre (world unit)", "seed": cfg.seed, "generator_version": GENERATOR_VERSION,
                "config": _config_record(cfg)}
    if cfg.water_type is not None:
        content["water_type"] = {"name": cfg.water_type, "wavelengths_nm": list(WAVELENGTHS_NM),
                                 "water_light": cfg.water_light, "sources": WATER_TYPE_SOURCES}
    if cfg.medium_profile != "homogeneous":
        formula = {"turbid-bottom": "1 + gain * exp(-max(z, 0) / height), z = height above the mean seabed",
                   "plume": "1 + gain * exp(-|x - center|^2 / (2 radius^2))"}[cfg.medium_profile]
        profile = {"kind": cfg.medium_profile, "gain": cfg.medium_profile_gain, "factor": formula,
                   "meaning": "beta_D(x) = beta_D * factor(x) and beta_B(x) = beta_B * factor(x), with beta_D and "
                              "beta_B above the reference values (factor 1); B_inf is one colour. A pixel sees the "
                              "mean of beta along its ray from the camera to the seabed."}
        if cfg.medium_profile == "turbid-bottom":
            profile["height"] = cfg.turbid_height
        else:
            profile |= {"radius": cfg.plume_radius, "center": list(cfg.plume_center)}
        content["medium_profile"] = profile
    path.write_text(json.dumps(content, indent=2, sort_keys=True) + "\n")


def generate_scene(config: SyntheticSceneConfig, out_dir: Path, progress: bool = True) -> Path:
    """Write the scene to `out_dir` (new or empty) in the SeaThru-NeRF layout plus gt/; returns `out_dir`.

    gt/medium.json is written last: its presence marks a complete scene (useful for caches).
    """
    out_dir = Path(out_dir)
    if out_dir.exists() and not out_dir.is_dir():
        raise ValueError(f"{out_dir} is a file, not a folder; write the scene to a new or empty folder")
    if out_dir.exists() and any(out_dir.iterdir()):
        # Never mix with (or delete) what is there: stale views of another scene would corrupt this one.
        raise ValueError(f"{out_dir} is not empty; write the scene to a new or empty folder")
    seeds = np.random.SeedSequence(config.seed).spawn(4)  # independent streams: poses, terrain, points, snow
    pose_rng, terrain_rng, point_rng, snow_rng = (np.random.default_rng(s) for s in seeds)
    K = intrinsics(config)
    medium = medium_parameters(config)
    with Progress(disable=not progress, transient=True) as bar:
        task = bar.add_task("seabed", total=config.num_views + 2)
        c2w = camera_poses(config, pose_rng)
        terrain = build_terrain(config, _focus_area(c2w), terrain_rng)
        _check_cameras(terrain, c2w)
        bar.update(task, advance=1, description="ray casting")
        views = []
        for k, pose in enumerate(c2w):
            views.append(render_view(config, terrain, K, pose, medium))
            if not config.open_water and not np.isfinite(views[-1].ranges).all():
                raise ValueError(f"view {k} looks above the horizon, where no seabed is: open_water off needs every "
                                 "ray to point down; lower tilt_deg")
            bar.advance(task)
        bar.update(task, description="writing")
        xyz, rgb = sample_points(config, views, K, point_rng)  # from the snow-free images: specks never triangulate
        if config.marine_snow > 0:
            snows = [marine_snow_particles(config, terrain, K, pose, snow_rng) for pose in c2w]
            for view, snow in zip(views, snows, strict=True):
                view.underwater = add_marine_snow(config, view, snow, medium)
            (out_dir / "gt").mkdir(parents=True, exist_ok=True)
            _write_marine_snow(out_dir / "gt" / "marine_snow.json", snows)
        _write_views(out_dir, views)
        write_colmap_model(out_dir / "sparse" / "0", K, config, c2w, xyz, rgb)
        z_bounds = np.stack([_z_bounds(v, k) for k, v in enumerate(views)])
        np.save(out_dir / "poses_bounds.npy", llff_poses_bounds(c2w, K, config, z_bounds))
        _write_medium(out_dir / "gt" / "medium.json", config, medium)
        bar.advance(task)
    return out_dir
