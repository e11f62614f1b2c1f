"""The synthetic scene and the SeaThru-NeRF layout reader: determinism, conventions, ground truth, errors."""

from __future__ import annotations

import dataclasses
import hashlib
import json
import shutil
from pathlib import Path

import numpy as np
import pycolmap
import pytest
from PIL import Image

from uw3dgs.data.seathru_layout import read_seathru_layout
from uw3dgs.datamanagers.synthetic.cli import entrypoint
from uw3dgs.datamanagers.synthetic.config import SyntheticSceneConfig, cache_key
from uw3dgs.datamanagers.synthetic.rendering import beta_field, medium_parameters, underwater_image
from uw3dgs.datamanagers.synthetic.scene import generate_scene
from uw3dgs.datamanagers.synthetic.water_types import (
    JERLOV_KD,
    SOLONENKO_MOBLEY_A,
    SOLONENKO_MOBLEY_B,
    WATER_TYPES,
    water_type,
)

# Small and quick; tilted enough that the far edge of the seabed leaves some open water in view.
SMALL = SyntheticSceneConfig(width=48, height=36, num_views=10, terrain_size=16.0, terrain_resolution=0.04,
                             tilt_deg=55.0, num_points=1000)
REAL_SCENE = Path(__file__).resolve().parents[2] / "shared" / "data" / "seathru-nerf" / "IUI3-RedSea"


@pytest.fixture(scope="module")
def scene_dir(tmp_path_factory) -> Path:
    return generate_scene(SMALL, tmp_path_factory.mktemp("synthetic") / "scene", progress=False)


@pytest.fixture
def scene_copy(scene_dir, tmp_path) -> Path:
    """A private copy to break."""
    return Path(shutil.copytree(scene_dir, tmp_path / "scene"))


def _files(root: Path) -> dict[str, bytes]:
    return {str(p.relative_to(root)): p.read_bytes() for p in sorted(root.rglob("*")) if p.is_file()}


def _pixel_dirs(K: np.ndarray, viewmat: np.ndarray, height: int, width: int) -> np.ndarray:
    """Unit world directions [H, W, 3] through the pixel centres (u + 0.5, v + 0.5)."""
    v, u = np.meshgrid(np.arange(height) + 0.5, np.arange(width) + 0.5, indexing="ij")
    cam = np.stack([(u - K[0, 2]) / K[0, 0], (v - K[1, 2]) / K[1, 1], np.ones_like(u)], axis=-1)
    world = cam @ viewmat[:3, :3]  # R^T applied to row vectors
    return world / np.linalg.norm(world, axis=-1, keepdims=True)


def _centre(viewmat: np.ndarray) -> np.ndarray:
    return -viewmat[:3, :3].T @ viewmat[:3, 3]


def test_layout_is_complete(scene_dir):
    names = [f"{k:04d}" for k in range(SMALL.num_views)]
    expected = {"poses_bounds.npy", "gt/medium.json", "sparse/0/cameras.bin", "sparse/0/images.bin",
                "sparse/0/points3D.bin"}
    expected |= {f"Images_wb/{n}.png" for n in names} | {f"gt/clean/{n}.png" for n in names}
    expected |= {f"gt/range/{n}.npy" for n in names}
    assert set(_files(scene_dir)) == expected
    medium = json.loads((scene_dir / "gt" / "medium.json").read_text())
    assert medium["units"] == "per metre (world unit)" and medium["seed"] == SMALL.seed
    assert medium["beta_D"] == pytest.approx(list(SMALL.beta_D))
    assert medium["config"]["width"] == SMALL.width
    assert Image.open(scene_dir / "Images_wb" / "0000.png").size == (SMALL.width, SMALL.height)


def test_deterministic_from_seed(scene_dir, tmp_path):
    again = generate_scene(SMALL, tmp_path / "again", progress=False)
    assert _files(again) == _files(scene_dir)
    other = _files(generate_scene(dataclasses.replace(SMALL, seed=1), tmp_path / "other", progress=False))
    reference = _files(scene_dir)
    for name in ("Images_wb/0000.png", "gt/range/0000.npy", "sparse/0/images.bin", "sparse/0/points3D.bin"):
        assert other[name] != reference[name], name


def test_cache_key_is_stable_and_config_specific():
    assert cache_key(SMALL) == cache_key(dataclasses.replace(SMALL))
    assert cache_key(SMALL) != cache_key(dataclasses.replace(SMALL, medium_strength=2.0))
    assert len(cache_key(SMALL)) == 12


def test_impossible_settings_are_refused(tmp_path):
    with pytest.raises(ValueError, match="width"):
        dataclasses.replace(SMALL, width=0)
    with pytest.raises(ValueError, match="increase altitude"):
        generate_scene(dataclasses.replace(SMALL, altitude=0.05), tmp_path / "buried", progress=False)
    (tmp_path / "used").mkdir()
    (tmp_path / "used" / "notes.txt").write_text("keep me")
    with pytest.raises(ValueError, match="not empty"):
        generate_scene(SMALL, tmp_path / "used", progress=False)


def test_pycolmap_reads_the_model(scene_dir):
    rec = pycolmap.Reconstruction(str(scene_dir / "sparse" / "0"))
    assert rec.num_cameras() == 1 and rec.num_images() == SMALL.num_views
    camera = next(iter(rec.cameras.values()))
    assert camera.model_name == "PINHOLE" and (camera.width, camera.height) == (SMALL.width, SMALL.height)
    fx, fy, cx, cy = camera.params
    assert fx == pytest.approx(0.5 * SMALL.width / np.tan(np.radians(SMALL.fov_deg / 2)))
    assert (fy, cx, cy) == (fx, SMALL.width / 2, SMALL.height / 2)
    assert sorted(im.name for im in rec.images.values()) == [f"{k:04d}.png" for k in range(SMALL.num_views)]
    assert rec.num_points3D() == SMALL.num_points


def test_reader_round_trip(scene_dir):
    scene = read_seathru_layout(scene_dir)
    n = SMALL.num_views
    assert scene.image_names == [f"{k:04d}.png" for k in range(n)]
    assert scene.images.shape == (n, SMALL.height, SMALL.width, 3)
    assert scene.gt is not None and scene.gt.ranges.shape == (n, SMALL.height, SMALL.width)
    assert scene.points.shape == scene.point_colors.shape == (SMALL.num_points, 3)
    finite = scene.gt.ranges[scene.gt.ranges.isfinite()]
    assert 0 < scene.near <= finite.min() and scene.far >= finite.max()


def test_ground_truth_is_consistent_across_views(scene_dir):
    """A surface point back-projected from view A with its true range lands, in view B, where B's true
    range says the surface is: poses and intrinsics follow one convention end to end."""
    scene = read_seathru_layout(scene_dir)
    ranges = scene.gt.ranges.double().numpy()
    for a, b in [(0, 1), (2, 4), (6, 7)]:
        cam_a, cam_b = scene.cameras[a], scene.cameras[b]
        va, vb = cam_a.viewmat.double().numpy(), cam_b.viewmat.double().numpy()
        dirs = _pixel_dirs(cam_a.K.double().numpy(), va, SMALL.height, SMALL.width)
        seen = np.isfinite(ranges[a])
        points = _centre(va) + dirs[seen] * ranges[a][seen, None]
        cam = points @ vb[:3, :3].T + vb[:3, 3]
        uv = cam @ cam_b.K.double().numpy().T
        x, y = uv[:, 0] / uv[:, 2] - 0.5, uv[:, 1] / uv[:, 2] - 0.5  # pixel-centre grid coordinates
        inside = (cam[:, 2] > 0) & (x >= 0) & (x < SMALL.width - 1) & (y >= 0) & (y < SMALL.height - 1)
        x, y, points = x[inside], y[inside], points[inside]
        j, i = x.astype(int), y.astype(int)
        wx, wy = x - j, y - i
        rb = ranges[b]
        expected = (rb[i, j] * (1 - wx) + rb[i, j + 1] * wx) * (1 - wy) + \
                   (rb[i + 1, j] * (1 - wx) + rb[i + 1, j + 1] * wx) * wy
        valid = np.isfinite(expected)
        rel = np.abs(np.linalg.norm(points - _centre(vb), axis=1)[valid] - expected[valid]) / expected[valid]
        assert valid.sum() > 100
        assert np.median(rel) < 0.005 and np.mean(rel < 0.02) > 0.9  # occlusions and silhouettes aside


def test_underwater_image_follows_the_formation_model(scene_dir):
    scene = read_seathru_layout(scene_dir)
    medium = scene.gt.medium
    beta_D, beta_B, B_inf = (np.array(medium[k]) for k in ("beta_D", "beta_B", "B_inf"))
    t = scene.gt.ranges.double().numpy()[..., None]
    clean, observed = scene.gt.clean_images.double().numpy(), scene.images.double().numpy()
    expected = clean * np.exp(-beta_D * t) + B_inf * (1 - np.exp(-beta_B * t))
    assert np.abs(observed - expected).max() <= 0.5 / 255 + 1e-5
    water = np.isinf(t[..., 0])
    assert 0.001 < water.mean() < 0.5  # this tilted config sees some open water beyond the seabed's edge
    assert (np.round(observed[water] * 255) == np.round(B_inf * 255)).all()
    assert (clean[water] == 0).all()
    assert scene.images.std() > 0.02 and scene.gt.clean_images.std() > 0.05  # textured, not flat


def test_clear_water_over_open_water_is_black_not_nan():
    """medium_strength 0 (beta = 0) where a pixel sees open water (t = inf): no light, no veil; 0 x inf is not NaN."""
    clean = np.array([[[0.0, 0.0, 0.0], [0.5, 0.4, 0.3]]])
    ranges = np.array([[np.inf, 2.0]])
    zero, veil = np.zeros(3), np.array([0.05, 0.25, 0.35])
    np.testing.assert_array_equal(underwater_image(clean, ranges, zero, zero, veil), clean)
    murky = underwater_image(clean, ranges, np.full(3, 0.3), np.full(3, 0.2), veil)
    np.testing.assert_allclose(murky[0, 0], veil)


def test_dark_patches_show_the_backscatter_alone(scene_dir):
    """Near-black seabed patches: there the underwater image is (almost) the backscatter B_inf (1 - exp(-beta_B t))."""
    scene = read_seathru_layout(scene_dir)
    medium = scene.gt.medium
    t = scene.gt.ranges.double().numpy()[..., None]
    dark = np.isfinite(t[..., 0]) & (scene.gt.clean_images.double().numpy() <= 0.04).all(-1)
    assert dark.mean() > 0.01
    backscatter = np.array(medium["B_inf"]) * (1 - np.exp(-np.array(medium["beta_B"]) * t))
    assert np.abs(scene.images.double().numpy() - backscatter)[dark].max() < 0.04 + 0.5 / 255


def test_a_scene_without_outliers(tmp_path):
    config = dataclasses.replace(SMALL, num_views=4, outlier_fraction=0.0, num_points=200)
    scene = read_seathru_layout(generate_scene(config, tmp_path / "scene", progress=False))
    assert len(scene.points) == 200


def test_points_lie_on_the_seen_seabed(scene_dir):
    """Most points (all but the outliers) sit within a few noise sigmas of the surface of view 0."""
    scene = read_seathru_layout(scene_dir)
    viewmat, K = scene.cameras[0].viewmat.double().numpy(), scene.cameras[0].K.double().numpy()
    points = scene.points.double().numpy()
    cam = points @ viewmat[:3, :3].T + viewmat[:3, 3]
    uv = cam @ K.T
    u, v = uv[:, 0] / uv[:, 2], uv[:, 1] / uv[:, 2]
    inside = (cam[:, 2] > 0) & (u >= 0) & (u < SMALL.width) & (v >= 0) & (v < SMALL.height)
    truth = scene.gt.ranges.double().numpy()[0][v[inside].astype(int), u[inside].astype(int)]
    dist = np.linalg.norm(points[inside] - _centre(viewmat), axis=1)
    close = np.abs(dist - truth) < 0.1 * truth
    assert inside.sum() > 50 and close.mean() > 0.75


def test_poses_bounds_agree_with_colmap(scene_dir):
    rows = np.load(scene_dir / "poses_bounds.npy")
    assert rows.shape == (SMALL.num_views, 17)
    rec = pycolmap.Reconstruction(str(scene_dir / "sparse" / "0"))
    images = sorted(rec.images.values(), key=lambda im: im.name)
    fx = next(iter(rec.cameras.values())).params[0]
    ranges = read_seathru_layout(scene_dir).gt.ranges.double().numpy()
    for row, image, t in zip(rows, images, ranges, strict=True):
        llff = row[:15].reshape(3, 5)
        # LLFF columns (down, right, back) -> OpenCV (right, down, forward)
        c2w = np.eye(4)
        c2w[:3, :3] = np.column_stack([llff[:, 1], llff[:, 0], -llff[:, 2]])
        c2w[:3, 3] = llff[:, 3]
        w2c = np.eye(4)
        w2c[:3] = image.cam_from_world().matrix()
        np.testing.assert_allclose(c2w @ w2c, np.eye(4), atol=1e-9)
        np.testing.assert_allclose(llff[:, 4], [SMALL.height, SMALL.width, fx])
        # near/far are the z-depths (not ranges) of the visible seabed, as LLFF stores them
        dirs = _pixel_dirs(np.array([[fx, 0, SMALL.width / 2], [0, fx, SMALL.height / 2], [0, 0, 1]]),
                           w2c, SMALL.height, SMALL.width)
        z = (t * (dirs @ c2w[:3, 2]))[np.isfinite(t)]
        np.testing.assert_allclose(row[15:], [z.min(), z.max()], rtol=1e-5)


def test_lawnmower_path(tmp_path):
    config = dataclasses.replace(SMALL, path="lawnmower", num_views=9, tilt_deg=30.0, num_points=200)
    scene = read_seathru_layout(generate_scene(config, tmp_path / "lawn", progress=False))
    centres = np.stack([c.center.numpy() for c in scene.cameras])
    lines = np.round(centres[:, 1] / config.line_spacing)  # lines run along x, spaced in y
    assert len(np.unique(lines)) == config.lawnmower_lines
    forward = np.stack([c.viewmat[2, :3].numpy() for c in scene.cameras])  # optical axes in world
    assert np.sign(forward[0, 0]) == -np.sign(forward[3, 0])  # alternate lines face opposite ways
    assert (forward[:, 2] < 0).all()  # looking down


def test_loop_path(tmp_path):
    config = dataclasses.replace(SMALL, path="loop", num_views=8, num_points=200)
    scene = read_seathru_layout(generate_scene(config, tmp_path / "loop", progress=False))
    centres = np.stack([c.center.numpy() for c in scene.cameras])
    radius = np.linalg.norm(centres[:, :2], axis=1)
    np.testing.assert_allclose(radius, config.loop_radius, atol=4 * config.pose_jitter)
    forward = np.stack([c.viewmat[2, :3].numpy() for c in scene.cameras])  # optical axes in world
    inward = -centres[:, :2] / radius[:, None]
    horizontal = forward[:, :2] / np.linalg.norm(forward[:, :2], axis=1, keepdims=True)
    assert ((horizontal * inward).sum(axis=1) > np.cos(np.radians(10))).all()  # facing the centre
    assert (forward[:, 2] < 0).all()  # looking down
    steps = np.linalg.norm(np.diff(centres[:, :2], axis=0, append=centres[:1, :2]), axis=1)
    assert steps.max() < 2 * steps.min()  # closed: the last view is as near the first as its other neighbour


def test_reader_variants(scene_copy):
    """Lower-case images_wb/, a SIMPLE_PINHOLE camera, and near/far from the points without poses_bounds."""
    (scene_copy / "Images_wb").rename(scene_copy / "images_wb")
    (scene_copy / "poses_bounds.npy").unlink()
    sparse = scene_copy / "sparse" / "0"
    rec = pycolmap.Reconstruction(str(sparse))
    fx, _, cx, cy = rec.cameras[1].params
    rec.cameras[1] = pycolmap.Camera(model="SIMPLE_PINHOLE", width=SMALL.width, height=SMALL.height,
                                     camera_id=1, params=[fx, cx, cy])
    rec.write_binary(str(sparse))
    scene = read_seathru_layout(scene_copy)
    assert scene.cameras[0].K[1, 1] == pytest.approx(fx)
    ranges = scene.gt.ranges[scene.gt.ranges.isfinite()]
    assert 0 < scene.near < ranges.median() < scene.far


def _write_opencv_camera(root: Path) -> None:
    sparse = root / "sparse" / "0"
    rec = pycolmap.Reconstruction(str(sparse))
    camera = rec.cameras[1]
    rec.cameras[1] = pycolmap.Camera(model="OPENCV", width=camera.width, height=camera.height, camera_id=1,
                                     params=[*camera.params, 0.01, 0.0, 0.0, 0.0])
    rec.write_binary(str(sparse))


def _resize_image(root: Path) -> None:
    path = root / "Images_wb" / "0003.png"
    Image.open(path).resize((SMALL.width // 2, SMALL.height // 2)).save(path)


def _truncate_image(root: Path) -> None:
    path = root / "Images_wb" / "0003.png"
    path.write_bytes(path.read_bytes()[:200])


@pytest.mark.parametrize(("corrupt", "error", "names"), [
    (lambda root: (root / "Images_wb" / "0003.png").unlink(), FileNotFoundError, ["0003.png", "images.bin"]),
    (_truncate_image, ValueError, ["0003.png"]),
    (_resize_image, ValueError, ["0003.png", "mixed image sizes"]),
    (_write_opencv_camera, ValueError, ["cameras.bin", "OPENCV", "undistort"]),
    (lambda root: shutil.rmtree(root / "sparse"), FileNotFoundError, ["sparse/0"]),
    (lambda root: shutil.rmtree(root / "Images_wb"), FileNotFoundError, ["Images_wb", "images_wb"]),
], ids=["missing-image", "truncated-image", "mixed-sizes", "distorted-camera", "no-model", "no-images"])
def test_reader_errors_name_the_file(scene_copy, corrupt, error, names):
    corrupt(scene_copy)
    with pytest.raises(error) as info:
        read_seathru_layout(scene_copy)
    for name in names:
        assert name in str(info.value), (name, str(info.value))


@pytest.mark.skipif(not REAL_SCENE.is_dir(), reason="real SeaThru-NeRF scene not present")
def test_reader_refuses_the_distorted_real_scene():
    with pytest.raises(ValueError, match="OPENCV"):
        read_seathru_layout(REAL_SCENE)


def test_cli_writes_a_scene(tmp_path, capsys):
    out = tmp_path / "cli"
    entrypoint(["--out", str(out), "--width", "32", "--height", "24", "--num-views", "4",
                "--num-points", "100", "--terrain-size", "12", "--terrain-resolution", "0.05",
                "--medium-strength", "2"])
    scene = read_seathru_layout(out)
    assert scene.images.shape == (4, 24, 32, 3)
    assert scene.gt.medium["beta_D"] == pytest.approx([0.8, 0.4, 0.24])
    assert "views" in capsys.readouterr().out


# Marine snow: transient bright particles, each drawn into one view only. Larger than the default particles so
# that they cover a pixel or more at this small width.
SNOWY = dataclasses.replace(SMALL, marine_snow=6, marine_snow_radius=(0.03, 0.05))


@pytest.fixture(scope="module")
def snowy_dir(tmp_path_factory) -> Path:
    return generate_scene(SNOWY, tmp_path_factory.mktemp("snowy") / "scene", progress=False)


def _particles(root: Path) -> list[dict]:
    return json.loads((root / "gt" / "marine_snow.json").read_text())["particles"]


def _footprint(particles: list[dict], view: int, margin: float = 1.5) -> np.ndarray:
    """[H, W] pixels within `margin` px of the discs of `view`'s particles."""
    v, u = np.meshgrid(np.arange(SMALL.height) + 0.5, np.arange(SMALL.width) + 0.5, indexing="ij")
    near = np.zeros((SMALL.height, SMALL.width), dtype=bool)
    for p in particles:
        if p["view"] == view:
            near |= np.hypot(u - p["uv"][0], v - p["uv"][1]) <= p["radius_px"] + margin
    return near


def test_marine_snow_is_off_by_default_and_keeps_the_keys():
    """Scenes without snow keep the cache keys (and bytes) they had before the option existed; the snow knobs
    only count once there is snow."""
    assert SyntheticSceneConfig().marine_snow == 0
    assert cache_key(SyntheticSceneConfig()) == "ecf3ad650b29"
    assert cache_key(SMALL) == "cde691d1356c"
    assert cache_key(dataclasses.replace(SMALL, marine_snow_radius=(0.1, 0.2), marine_snow_brightness=0.5)) == \
        cache_key(SMALL)
    assert cache_key(SNOWY) != cache_key(SMALL)
    assert cache_key(SNOWY) != cache_key(dataclasses.replace(SNOWY, marine_snow_brightness=0.5))


def test_marine_snow_leaves_the_truth_alone(scene_dir, snowy_dir):
    """Snow is part of the water, not the scene: clean images, ranges, poses, points and medium are those of
    the snow-free scene; only the underwater images differ, and the particles are listed."""
    plain, snowy = _files(scene_dir), _files(snowy_dir)
    assert set(snowy) == set(plain) | {"gt/marine_snow.json"}
    for name in plain:
        if not name.startswith("Images_wb/") and name != "gt/medium.json":
            assert snowy[name] == plain[name], name
    medium, snowy_medium = (json.loads((d / "gt" / "medium.json").read_text()) for d in (scene_dir, snowy_dir))
    assert "marine_snow" not in medium["config"] and snowy_medium["config"]["marine_snow"] == SNOWY.marine_snow
    for key in ("beta_D", "beta_B", "B_inf"):
        assert snowy_medium[key] == medium[key]
    assert sum(snowy[n] != plain[n] for n in plain if n.startswith("Images_wb/")) == SNOWY.num_views
    assert len(_particles(snowy_dir)) == SNOWY.marine_snow * SNOWY.num_views


def test_marine_snow_adds_small_bright_specks(scene_dir, snowy_dir):
    """Each view differs from the snow-free one only in small discs around its own particles, where it is
    brighter; each particle in front of its pixel's seabed shows."""
    plain, snowy = read_seathru_layout(scene_dir), read_seathru_layout(snowy_dir)
    ranges = plain.gt.ranges.numpy()
    particles = _particles(snowy_dir)
    for k in range(SNOWY.num_views):
        before, after = (np.round(s.images[k].double().numpy() * 255) for s in (plain, snowy))
        changed = (after != before).any(axis=-1)
        assert (after >= before).all()  # a particle is brighter than what it hides, in every channel
        assert 0 < changed.mean() < 0.1
        assert not (changed & ~_footprint(particles, k)).any()  # only near this view's own particles
        shown = 0
        for p in (p for p in particles if p["view"] == k):
            assert 0 < p["range"] < ranges[k][int(p["uv"][1]), int(p["uv"][0])] + 0.05  # never behind the seabed
            assert SNOWY.marine_snow_range[0] / 2 <= p["range"] <= SNOWY.marine_snow_range[1]
            shown += changed[int(p["uv"][1]), int(p["uv"][0])]
        assert shown >= SNOWY.marine_snow - 1  # a particle may hide behind a rock edge


def test_marine_snow_is_transient(scene_dir, snowy_dir):
    """A particle of view k is in no other view: where it projects into view j (in front of j's seabed, away
    from j's own particles), view j is exactly the snow-free image."""
    plain, snowy = read_seathru_layout(scene_dir), read_seathru_layout(snowy_dir)
    ranges = plain.gt.ranges.numpy()
    particles = _particles(snowy_dir)
    checked = 0
    for j, cam in enumerate(plain.cameras):
        viewmat, K = cam.viewmat.double().numpy(), cam.K.double().numpy()
        own = _footprint(particles, j)
        for p in (p for p in particles if p["view"] != j):
            xyz = np.array(p["xyz"])
            x_cam = viewmat[:3, :3] @ xyz + viewmat[:3, 3]
            if x_cam[2] <= 0:
                continue
            u, v = (K @ x_cam)[:2] / x_cam[2]
            if not (0 <= u < SMALL.width and 0 <= v < SMALL.height) or own[int(v), int(u)]:
                continue
            if np.linalg.norm(xyz - _centre(viewmat)) >= ranges[j][int(v), int(u)]:
                continue  # behind view j's seabed: it would be hidden anyway
            assert (snowy.images[j, int(v), int(u)] == plain.images[j, int(v), int(u)]).all(), (p, j)
            checked += 1
    assert checked > 20


def test_marine_snow_is_deterministic(tmp_path):
    config = dataclasses.replace(SNOWY, num_views=3, num_points=100)
    first = _files(generate_scene(config, tmp_path / "a", progress=False))
    assert first == _files(generate_scene(config, tmp_path / "b", progress=False))
    other = _files(generate_scene(dataclasses.replace(config, seed=1), tmp_path / "c", progress=False))
    assert other["gt/marine_snow.json"] != first["gt/marine_snow.json"]


@pytest.mark.parametrize(("change", "name"), [
    ({"marine_snow": -1}, "marine_snow"),
    ({"marine_snow": 1.5}, "marine_snow"),
    ({"marine_snow_range": (3.0, 1.0)}, "marine_snow_range"),
    ({"marine_snow_range": (0.0, 1.0)}, "marine_snow_range"),
    ({"marine_snow_radius": (0.05, 0.01)}, "marine_snow_radius"),
    ({"marine_snow_brightness": 1.5}, "marine_snow_brightness"),
])
def test_marine_snow_options_are_checked(change, name):
    with pytest.raises(ValueError, match=name):
        dataclasses.replace(SMALL, **change)


def test_cli_writes_marine_snow(tmp_path):
    out = tmp_path / "cli"
    entrypoint(["--out", str(out), "--width", "32", "--height", "24", "--num-views", "2", "--num-points", "50",
                "--terrain-size", "12", "--terrain-resolution", "0.05", "--marine-snow", "3",
                "--marine-snow-radius", "0.02", "0.04"])
    particles = _particles(out)
    assert len(particles) == 6 and {p["view"] for p in particles} == {0, 1}
    assert all(0.02 <= p["radius"] <= 0.04 for p in particles)


# Scene variants: water types, darkest albedo, open water, range span, a spatially varying medium. Each is
# one option away, and the default scene keeps its bytes and cache key.
TINY = dataclasses.replace(SMALL, width=32, height=24, num_views=3, num_points=100, terrain_size=12.0,
                           terrain_resolution=0.05)


def _pixels(root: Path) -> np.ndarray:
    return np.stack([np.asarray(Image.open(p)) for p in sorted((root / "Images_wb").glob("*.png"))])


def _digest(array: np.ndarray) -> str:
    return hashlib.sha256(np.ascontiguousarray(array).tobytes()).hexdigest()[:16]


def test_the_default_scene_is_unchanged_by_the_variants(scene_dir):
    """Keys and pixels computed before the variant options existed: a knob that is off changes nothing."""
    assert cache_key(SyntheticSceneConfig()) == "ecf3ad650b29"
    assert cache_key(SMALL) == "cde691d1356c"
    assert _digest(_pixels(scene_dir)) == "5c291a9cd3a64f02"
    ranges = np.stack([np.load(p) for p in sorted((scene_dir / "gt" / "range").glob("*.npy"))])
    assert _digest(ranges) == "3b71d48f0cc2e1a2"
    medium = json.loads((scene_dir / "gt" / "medium.json").read_text())
    assert not {"water_type", "medium_profile"} & set(medium)
    assert not {"water_type", "open_water", "medium_profile", "plume_center"} & set(medium["config"])
    # knobs of a profile that is off do not count
    assert cache_key(dataclasses.replace(SMALL, turbid_height=5.0, plume_radius=0.5)) == cache_key(SMALL)
    assert cache_key(dataclasses.replace(SMALL, medium_profile="turbid-bottom", plume_center=(1.0, 1.0, 1.0))) == \
        cache_key(dataclasses.replace(SMALL, medium_profile="turbid-bottom"))
    for change in ({"water_type": "II"}, {"open_water": False}, {"medium_profile": "plume"}):
        assert cache_key(dataclasses.replace(SMALL, **change)) != cache_key(SMALL), change


def test_water_types_are_the_cited_tables():
    """Jerlov (1976) Table XXVII K_d and Solonenko & Mobley (2015) a, b, at 600, 525, 475 nm (R, G, B)."""
    assert WATER_TYPES == ("I", "II", "III", "1C", "3C", "5C", "7C", "9C")
    assert JERLOV_KD["I"] == (0.235, 0.043, 0.018) and JERLOV_KD["9C"] == (0.60, 0.78, 1.23)
    assert SOLONENKO_MOBLEY_A["1C"] == (0.236, 0.068, 0.077) and SOLONENKO_MOBLEY_B["1C"] == (0.314, 0.395, 0.469)
    assert SOLONENKO_MOBLEY_B["7C"] == (2.03, 2.54, 3.01)
    coastal = water_type("3C")
    assert coastal.beta_D == coastal.beta_B == (0.33, 0.20, 0.29)
    np.testing.assert_allclose(coastal.B_inf, [0.916 / 1.155, 1.15 / 1.228, 1.36 / 1.465])
    clear = water_type("I")  # almost no particles: a dark blue veil
    assert clear.B_inf[0] < 0.01 < clear.B_inf[1] < clear.B_inf[2] < 0.2
    medium = medium_parameters(SyntheticSceneConfig(water_type="9C", medium_strength=2.0, water_light=0.5))
    np.testing.assert_allclose(medium["beta_D"], [1.2, 1.56, 2.46])
    np.testing.assert_allclose(medium["B_inf"], 0.5 * np.array(water_type("9C").B_inf))


@pytest.mark.parametrize("name", ["I", "9C"])
def test_a_water_type_scene_follows_its_medium(tmp_path, name):
    root = generate_scene(dataclasses.replace(TINY, water_type=name), tmp_path / name, progress=False)
    scene = read_seathru_layout(root)
    medium = scene.gt.medium
    water = water_type(name)
    assert medium["beta_D"] == pytest.approx(water.beta_D) and medium["B_inf"] == pytest.approx(water.B_inf)
    assert medium["water_type"]["name"] == name and medium["water_type"]["wavelengths_nm"] == [600, 525, 475]
    t = scene.gt.ranges.double().numpy()[..., None]
    expected = scene.gt.clean_images.double().numpy() * np.exp(-np.array(water.beta_D) * t) + \
        np.array(water.B_inf) * (1 - np.exp(-np.array(water.beta_B) * t))
    assert np.abs(scene.images.double().numpy() - expected).max() <= 0.5 / 255 + 1e-5


def test_darkest_albedo_variants(tmp_path):
    """dark_patch_albedo 0.03 (default), 0.1, 0.2: the darkest seabed brightens, as real sand and rock are darkest."""
    darkest = []
    for albedo in (0.03, 0.1, 0.2):
        scene = read_seathru_layout(generate_scene(dataclasses.replace(TINY, dark_patch_albedo=albedo),
                                                   tmp_path / str(albedo), progress=False))
        seabed = scene.gt.clean_images.numpy()[np.isfinite(scene.gt.ranges.numpy())]
        darkest.append(np.percentile(seabed.max(axis=-1), 1))
    assert darkest[0] < 0.04 and darkest[0] < darkest[1] < darkest[2]


def test_without_open_water(scene_dir, tmp_path):
    """open_water off: the seabed goes on beyond its square, so no ray sees open water; the seabed inside the square
    (what the default scene shows) is the same, and the formation model holds."""
    root = generate_scene(dataclasses.replace(SMALL, open_water=False), tmp_path / "closed", progress=False)
    closed, open_ = read_seathru_layout(root), read_seathru_layout(scene_dir)
    ranges, before = closed.gt.ranges.double().numpy(), open_.gt.ranges.double().numpy()
    assert np.isfinite(ranges).all() and np.isinf(before).mean() > 0.05
    seen = np.isfinite(before)
    assert np.mean(np.abs(ranges[seen] - before[seen]) < 1e-3 * before[seen]) > 0.99
    assert ranges.max() > before[seen].max()  # the far end now reaches past the square's edge
    medium = closed.gt.medium
    t = ranges[..., None]
    expected = closed.gt.clean_images.double().numpy() * np.exp(-np.array(medium["beta_D"]) * t) + \
        np.array(medium["B_inf"]) * (1 - np.exp(-np.array(medium["beta_B"]) * t))
    assert np.abs(closed.images.double().numpy() - expected).max() <= 0.5 / 255 + 1e-5
    with pytest.raises(ValueError, match="lower tilt_deg"):  # rays above the horizon never meet the seabed
        generate_scene(dataclasses.replace(TINY, open_water=False, tilt_deg=80.0), tmp_path / "sky", progress=False)


def test_a_narrow_range_span(tmp_path):
    """Range span variant: 1.5 m up, looking nearly straight down (tilt 5 degrees from nadir)."""
    config = dataclasses.replace(TINY, altitude=1.5, tilt_deg=5.0)
    ranges = read_seathru_layout(generate_scene(config, tmp_path / "narrow", progress=False)).gt.ranges.numpy()
    assert np.isfinite(ranges).all()
    assert ranges.min() > 0.5 and ranges.max() < 3.0 and ranges.max() / ranges.min() < 3.0


def _profile_factor(profile: dict, points: np.ndarray) -> np.ndarray:
    """The factor written in gt/medium.json, evaluated here on its own (float64)."""
    if profile["kind"] == "turbid-bottom":
        return 1.0 + profile["gain"] * np.exp(-np.maximum(points[..., 2], 0.0) / profile["height"])
    d2 = ((points - np.array(profile["center"])) ** 2).sum(-1)
    return 1.0 + profile["gain"] * np.exp(-d2 / (2 * profile["radius"] ** 2))


@pytest.mark.parametrize("profile", ["turbid-bottom", "plume"])
def test_a_varying_medium_follows_the_ray_mean_model(tmp_path, profile):
    """Each pixel is J exp(-int beta_D) + B_inf (1 - exp(-int beta_B)) along its ray, integrated here by brute force
    (20,000 samples, float64) from the profile written to gt/medium.json; open water is B_inf alone."""
    config = dataclasses.replace(TINY, medium_profile=profile)
    scene = read_seathru_layout(generate_scene(config, tmp_path / profile, progress=False))
    medium = scene.gt.medium
    beta_D, beta_B, B_inf = (np.array(medium[k]) for k in ("beta_D", "beta_B", "B_inf"))
    assert beta_D == pytest.approx(list(TINY.beta_D))  # gt/medium.json keeps the reference medium
    rng = np.random.default_rng(0)
    s = (np.arange(20000) + 0.5) / 20000
    spread = []
    for k, cam in enumerate(scene.cameras):
        viewmat = cam.viewmat.double().numpy()
        dirs = _pixel_dirs(cam.K.double().numpy(), viewmat, TINY.height, TINY.width)
        ranges = scene.gt.ranges[k].double().numpy()
        observed, clean = scene.images[k].double().numpy(), scene.gt.clean_images[k].double().numpy()
        water = np.isinf(ranges)
        assert (np.round(observed[water] * 255) == np.round(B_inf * 255)).all()
        for i, j in zip(*(a[:25] for a in np.nonzero(~water & (rng.random(water.shape) < 0.2))), strict=True):
            points = _centre(viewmat) + dirs[i, j] * (ranges[i, j] * s)[:, None]
            optical = _profile_factor(medium["medium_profile"], points).mean() * ranges[i, j]
            spread.append(optical / ranges[i, j])
            expected = clean[i, j] * np.exp(-beta_D * optical) + B_inf * (1 - np.exp(-beta_B * optical))
            assert np.abs(observed[i, j] - expected).max() <= 0.5 / 255 + 1e-5, (k, i, j)
    assert len(spread) >= 50 and max(spread) > 1.3  # the medium along the rays is far from the reference


def test_the_turbid_bottom_field_grows_towards_the_seabed():
    config = SyntheticSceneConfig(medium_profile="turbid-bottom", medium_profile_gain=3.0, turbid_height=1.0)
    heights = np.array([-0.5, 0.0, 0.25, 0.5, 1.0, 2.0, 4.0, 30.0])
    beta_D, beta_B = beta_field(config, np.stack([np.zeros(8), np.ones(8), heights], axis=1))
    reference = np.array(config.beta_D)
    np.testing.assert_allclose(beta_D[:2], 4.0 * np.stack([reference] * 2))  # (1 + gain) x at and below the seabed
    np.testing.assert_allclose(beta_D[-1], reference, rtol=1e-9)
    assert (np.diff(beta_D[1:], axis=0) < 0).all() and (np.diff(beta_B[1:], axis=0) < 0).all()
    plume = dataclasses.replace(config, medium_profile="plume", plume_center=(1.0, 2.0, 1.5), plume_radius=1.0)
    centre, far = beta_field(plume, np.array([[1.0, 2.0, 1.5], [1.0, 12.0, 1.5]]))[1]
    np.testing.assert_allclose(centre, 4.0 * np.array(config.beta_B))
    np.testing.assert_allclose(far, config.beta_B)
    homogeneous = beta_field(SyntheticSceneConfig(), np.zeros((2, 3)))[0]
    np.testing.assert_allclose(homogeneous, [SyntheticSceneConfig().beta_D] * 2)


def test_marine_snow_in_a_varying_medium(tmp_path):
    """Particles are seen through the mean beta along their own ray; pixels away from them keep their bytes."""
    plain = dataclasses.replace(TINY, medium_profile="plume")
    snowy = dataclasses.replace(plain, marine_snow=4, marine_snow_radius=(0.03, 0.05))
    before = _pixels(generate_scene(plain, tmp_path / "plain", progress=False)).astype(int)
    root = generate_scene(snowy, tmp_path / "snowy", progress=False)
    after = _pixels(root).astype(int)
    changed = (after != before).any(-1)
    assert (after >= before).all() and 0 < changed.mean() < 0.2
    for k in range(TINY.num_views):
        v, u = np.meshgrid(np.arange(TINY.height) + 0.5, np.arange(TINY.width) + 0.5, indexing="ij")
        near = np.zeros_like(changed[k])
        for p in (p for p in _particles(root) if p["view"] == k):
            near |= np.hypot(u - p["uv"][0], v - p["uv"][1]) <= p["radius_px"] + 1.5
        assert not (changed[k] & ~near).any()


@pytest.mark.parametrize(("change", "name"), [
    ({"water_type": "IA"}, "water_type"),  # Jerlov tabulates IA, but no cited b gives its B_inf
    ({"water_type": "1C", "beta_D": (1.0, 1.0, 1.0)}, "beta_D"),
    ({"water_type": "1C", "B_inf": (0.1, 0.1, 0.1)}, "B_inf"),
    ({"water_type": "1C", "water_light": 1.5}, "water_light"),
    ({"water_light": 0.5}, "water_light"),
    ({"medium_profile": "fog"}, "medium_profile"),
    ({"medium_profile_gain": -1.0}, "medium_profile_gain"),
    ({"turbid_height": 0.0}, "turbid_height"),
    ({"plume_radius": -1.0}, "plume_radius"),
    ({"plume_center": (0.0, float("nan"), 1.0)}, "plume_center"),
])
def test_variant_options_are_checked(change, name):
    with pytest.raises(ValueError, match=name):
        dataclasses.replace(SMALL, **change)


def test_cli_writes_a_variant(tmp_path):
    out = tmp_path / "cli"
    entrypoint(["--out", str(out), "--width", "32", "--height", "24", "--num-views", "2", "--num-points", "50",
                "--terrain-size", "12", "--terrain-resolution", "0.05", "--water-type", "1C", "--no-open-water",
                "--medium-profile", "turbid-bottom", "--turbid-height", "0.5"])
    scene = read_seathru_layout(out)
    assert scene.gt.ranges.isfinite().all()
    medium = scene.gt.medium
    assert medium["beta_D"] == pytest.approx(list(JERLOV_KD["1C"])) and medium["water_type"]["name"] == "1C"
    assert (medium["medium_profile"]["kind"], medium["medium_profile"]["height"]) == ("turbid-bottom", 0.5)
    assert (medium["config"]["water_type"], medium["config"]["open_water"]) == ("1C", False)
