"""The procedural seabed: heights from layered noise, an albedo texture (sand, algae, rocks, encrusting life,
specks, dark patches) and its shading."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from uw3dgs.datamanagers.synthetic.config import SyntheticSceneConfig

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
