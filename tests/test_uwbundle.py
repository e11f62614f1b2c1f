"""UWBundle: .calib and PLY readers, geometry helpers, and structure from motion on a synthetic stereo capture.

The fixture renders the built-in procedural seabed (datamanagers/synthetic/scene.py) through two distorted
cameras 12 cm apart (the left one with k3 != 0, so FULL_OPENCV; the right one OPENCV), 10 stereo pairs at
160x120, and writes it in the UWBundle layout with a .calib and the true surface as groundtruth.ply.
"""

from __future__ import annotations

import shutil
import struct
import time
from pathlib import Path

import numpy as np
import pycolmap
import pytest
import torch
from PIL import Image

from uw3dgs.data import sfm
from uw3dgs.data.colmap_dataset import denormalize_points
from uw3dgs.data.datamanager import AutoDataManagerConfig
from uw3dgs.data.sfm import FixedCamera, SfmError, run_sfm
from uw3dgs.datamanagers import uwbundle
from uw3dgs.datamanagers.synthetic.cameras import camera_poses
from uw3dgs.datamanagers.synthetic.config import SyntheticSceneConfig
from uw3dgs.datamanagers.synthetic.rendering import medium_parameters, underwater_image
from uw3dgs.datamanagers.synthetic.terrain import build_terrain
from uw3dgs.datamanagers.uwbundle import (
    CalibCamera,
    CalibError,
    StereoCalibration,
    UWBundleDataManagerConfig,
    apply_similarity,
    distance_to_ground_truth,
    read_calib,
    read_ply_points,
    read_uwbundle,
    umeyama,
    write_calib,
    write_ply_points,
)

# A diver's forward pass 3 m above the seabed, looking 20 degrees ahead of straight down. (At 35 degrees these
# tiny images make COLMAP's initial-pair search relax its constraints, and most runs settle in a wrong local
# minimum, which the stereo check catches: see test_sfm_retries_a_model_that_fails_the_quality_check.)
CFG = SyntheticSceneConfig(width=160, height=120, num_views=10, terrain_size=12.0, path_length=3.0,
                           pose_jitter=0.03, angle_jitter_deg=1.0, tilt_deg=20.0)
W, H = CFG.width, CFG.height
BASELINE = 0.12
_ANGLE = np.radians(1.0)  # the right camera toes in by 1 degree
R_RIGHT = np.array([[np.cos(_ANGLE), 0, -np.sin(_ANGLE)], [0, 1, 0], [np.sin(_ANGLE), 0, np.cos(_ANGLE)]])
LEFT = CalibCamera(W, H, np.array([[140.0, 0, 79.3], [0, 141.0, 60.2], [0, 0, 1]]),
                   np.array([-0.12, 0.04, 0.001, -0.0015, 0.01]), np.eye(3), np.zeros(3))
RIGHT = CalibCamera(W, H, np.array([[138.0, 0, 80.6], [0, 138.5, 59.1], [0, 0, 1]]),
                    np.array([-0.10, 0.03, -0.001, 0.001, 0.0]), R_RIGHT, -R_RIGHT @ np.array([BASELINE, 0, 0]))
GT_SPACING = 0.05


def _render(terrain, camera: pycolmap.Camera, c2w: np.ndarray, medium: dict) -> np.ndarray:
    """One underwater image through a distorted camera: each pixel centre's ray comes from COLMAP's own
    inverse projection (cam_from_img), so the images follow exactly the model SfM will be given."""
    v, u = np.meshgrid(np.arange(H) + 0.5, np.arange(W) + 0.5, indexing="ij")
    xy = camera.cam_from_img(np.stack([u.ravel(), v.ravel()], axis=-1))
    dirs = np.column_stack([xy, np.ones(len(xy))]) @ c2w[:3, :3].T
    dirs /= np.linalg.norm(dirs, axis=1, keepdims=True)
    t = terrain.cast(c2w[:3, 3], dirs, CFG.march_steps)
    hit = np.isfinite(t)
    p = c2w[:3, 3] + dirs * np.where(hit, t, 0.0)[:, None]
    clean = terrain.radiance_at(p[:, 0], p[:, 1]) * hit[:, None]
    image = underwater_image(clean, t, medium["beta_D"], medium["beta_B"], medium["B_inf"])
    return np.round(np.clip(image, 0, 1) * 255).astype(np.uint8).reshape(H, W, 3)


def write_fixture(root: Path) -> dict[str, np.ndarray]:
    """The UWBundle-layout capture; returns the true camera centre of every image name."""
    pose_rng, terrain_rng = (np.random.default_rng(s) for s in np.random.SeedSequence(0).spawn(2))
    c2w = camera_poses(CFG, pose_rng)
    centres = c2w[:, :3, 3]
    focus = np.array([centres[:, 0].min() - 2, centres[:, 0].max() + 2, centres[:, 1].min() - 1,
                      centres[:, 1].max() + 4])  # where the forward-tilted cameras look: rocks go there
    terrain = build_terrain(CFG, focus, terrain_rng)
    medium = medium_parameters(CFG)
    left_from_right = np.eye(4)
    left_from_right[:3, :3], left_from_right[:3, 3] = R_RIGHT.T, -R_RIGHT.T @ RIGHT.t
    truth = {}
    for side, calib, extrinsic in (("left", LEFT, np.eye(4)), ("right", RIGHT, left_from_right)):
        fixed = calib.fixed_camera()
        camera = pycolmap.Camera.create_from_model_name(1, fixed.model, 1.0, W, H)
        camera.params = list(fixed.params)
        (root / side).mkdir(parents=True)
        for k, pose in enumerate(c2w):
            world_from_cam = pose @ extrinsic
            Image.fromarray(_render(terrain, camera, world_from_cam, medium)).save(root / side / f"{k:04d}.png")
            truth[f"{side}/{k:04d}.png"] = world_from_cam[:3, 3]
    write_calib(root / "stereo.calib", StereoCalibration(LEFT, RIGHT, np.concatenate([np.eye(3).ravel(),
                                                                                     R_RIGHT.ravel()])))
    lo, hi = terrain.extent
    grid = np.arange(lo, hi, GT_SPACING)
    gx, gy = (a.ravel() for a in np.meshgrid(grid, grid))
    write_ply_points(root / "groundtruth.ply", np.column_stack([gx, gy, terrain.height_at(gx, gy)]))
    return truth


@pytest.fixture(scope="module")
def capture(tmp_path_factory) -> tuple[Path, dict[str, np.ndarray]]:
    root = tmp_path_factory.mktemp("uwbundle") / "pool"
    return root, write_fixture(root)


@pytest.fixture(scope="module")
def loaded(capture, tmp_path_factory):
    """The first load (structure from motion), timed; the dataset folder is writable, so the model goes there."""
    root, _ = capture
    cache = tmp_path_factory.mktemp("cache")
    start = time.perf_counter()
    scene = read_uwbundle(root, cache_dir=cache, progress=False)
    return scene, cache, time.perf_counter() - start


# ----------------------------------------------------------------------------------------------------
# .calib


def _assert_same(a: StereoCalibration, b: StereoCalibration) -> None:
    for ca, cb in ((a.left, b.left), (a.right, b.right)):
        assert (ca.width, ca.height) == (cb.width, cb.height)
        for name in ("K", "dist", "R", "t"):
            np.testing.assert_array_equal(getattr(ca, name), getattr(cb, name))
    np.testing.assert_array_equal(a.rectification, b.rectification)


def test_calib_round_trip(tmp_path):
    calib = StereoCalibration(LEFT, RIGHT, np.arange(58, dtype=float) / 7)  # R1 R2 P1 P2 Q of stereoRectify
    write_calib(tmp_path / "a.calib", calib)
    back = read_calib(tmp_path / "a.calib")
    _assert_same(back, calib)
    assert back.baseline == pytest.approx(BASELINE)
    R, t = back.right_from_left()
    np.testing.assert_allclose(R, R_RIGHT)
    np.testing.assert_allclose(-R.T @ t, [BASELINE, 0, 0], atol=1e-15)  # right centre in the left frame


def test_calib_free_layout(tmp_path):
    """Line breaks, labels and comments do not matter; numbers are read in order."""
    numbers = lambda c: [float(x) for x in (c.width, c.height, *c.K.ravel(), *c.dist, *c.R.ravel(), *c.t)]  # noqa: E731
    text = ["% stereo rig, tank test", "Left camera", "size: " + " ".join(map(repr, numbers(LEFT)[:2])),
            "K1: " + " ".join(map(repr, numbers(LEFT)[2:11])) + "   # row-major",
            " ".join(map(repr, numbers(LEFT)[11:])), "", "[right]"]
    text += [repr(x) for x in numbers(RIGHT)]  # one number per line
    (tmp_path / "b.calib").write_text("\n".join(text) + "\n")
    _assert_same(read_calib(tmp_path / "b.calib"), StereoCalibration(LEFT, RIGHT))


@pytest.mark.parametrize("break_it, line, words", [
    (lambda lines: lines.__setitem__(4, "0.0 141.0 sixty"), 5, "'sixty' is not a number"),
    (lambda lines: lines.__setitem__(8, "1.0 0.0 0.5"), 8, "not a rotation"),
    (lambda lines: lines.__setitem__(2, "160.5 120"), 3, "two positive integers"),
    (lambda lines: lines.__setitem__(5, "0.0 1.0 1.0"), 4, "not a camera matrix"),
    (lambda lines: lines.__delitem__(slice(16, None)), 16, "ends after 39 numbers, in the right camera's distortion"),
])
def test_malformed_calib_names_file_and_line(tmp_path, break_it, line, words):
    write_calib(tmp_path / "good.calib", StereoCalibration(LEFT, RIGHT))
    lines = (tmp_path / "good.calib").read_text().splitlines()
    break_it(lines)
    (tmp_path / "bad.calib").write_text("\n".join(lines) + "\n")
    with pytest.raises(CalibError, match=words) as err:
        read_calib(tmp_path / "bad.calib")
    assert f"bad.calib:{line}:" in str(err.value)


def test_fixed_camera_matches_opencv_projection():
    """OPENCV for k3 = 0, FULL_OPENCV (k4..k6 = 0) otherwise, both projecting exactly as OpenCV's 5-parameter
    model with the half-pixel shift between OpenCV's and COLMAP's pixel coordinates."""
    assert RIGHT.fixed_camera().model == "OPENCV" and LEFT.fixed_camera().model == "FULL_OPENCV"
    rng = np.random.default_rng(0)
    points = np.column_stack([rng.uniform(-0.6, 0.6, (200, 2)), np.ones(200)])
    for calib in (LEFT, RIGHT):
        fixed = calib.fixed_camera()
        camera = pycolmap.Camera.create_from_model_name(1, fixed.model, 1.0, W, H)
        camera.params = list(fixed.params)
        x, y = points[:, 0], points[:, 1]
        k1, k2, p1, p2, k3 = calib.dist
        r2 = x * x + y * y
        radial = 1 + k1 * r2 + k2 * r2**2 + k3 * r2**3
        xd = x * radial + 2 * p1 * x * y + p2 * (r2 + 2 * x * x)
        yd = y * radial + p1 * (r2 + 2 * y * y) + 2 * p2 * x * y
        opencv = np.column_stack([xd, yd, np.ones_like(xd)]) @ calib.K.T
        np.testing.assert_allclose(camera.img_from_cam(points) - 0.5, opencv[:, :2], atol=1e-9)


def test_rescaled_camera():
    fixed = RIGHT.fixed_camera().rescaled(2 * W, 2 * H)
    assert fixed.params[:4] == pytest.approx([276.0, 277.0, 2 * 81.1, 2 * 59.6])
    assert fixed.params[4:] == RIGHT.fixed_camera().params[4:]
    with pytest.raises(ValueError, match="aspect ratio"):
        RIGHT.fixed_camera().rescaled(W, W)


# ----------------------------------------------------------------------------------------------------
# PLY


def test_ply_binary_and_ascii_round_trip(tmp_path):
    points = np.random.default_rng(0).normal(size=(500, 3)).astype(np.float32)
    for binary in (True, False):
        write_ply_points(tmp_path / "p.ply", points, binary=binary)
        np.testing.assert_array_equal(read_ply_points(tmp_path / "p.ply"), points.astype(np.float64))


def test_ply_meshes_with_colours_faces_and_big_endian(tmp_path):
    xyz = np.array([[0.0, 0.0, 0.0], [1.0, 0.0, 0.5], [0.0, 1.0, -2.25], [1.5, 1.0, 3.0]])
    colours = np.array([[255, 0, 0], [0, 255, 0], [0, 0, 255], [9, 9, 9]], dtype=np.uint8)
    faces = [[0, 1, 2], [1, 3, 2]]
    props = "property double x\nproperty double y\nproperty double z\n" \
            "property uchar red\nproperty uchar green\nproperty uchar blue\n"
    face = "element face 2\nproperty list uchar int vertex_indices\n"
    # ASCII mesh: vertices with colours, then faces
    ascii_body = "".join(f"{x} {y} {z} {r} {g} {b}\n" for (x, y, z), (r, g, b) in zip(xyz, colours, strict=True))
    ascii_body += "".join("3 " + " ".join(map(str, f)) + "\n" for f in faces)
    (tmp_path / "a.ply").write_text(f"ply\nformat ascii 1.0\nelement vertex 4\n{props}{face}end_header\n{ascii_body}")
    np.testing.assert_array_equal(read_ply_points(tmp_path / "a.ply"), xyz)
    # big-endian binary with the faces first (a list property to walk over before the vertices)
    body = b"".join(struct.pack(">B3i", 3, *f) for f in faces)
    body += b"".join(struct.pack(">3d3B", *p, *c) for p, c in zip(xyz, colours, strict=True))
    header = f"ply\nformat binary_big_endian 1.0\ncomment faces first\n{face}element vertex 4\n{props}end_header\n"
    (tmp_path / "b.ply").write_bytes(header.encode() + body)
    np.testing.assert_array_equal(read_ply_points(tmp_path / "b.ply"), xyz)
    (tmp_path / "c.ply").write_bytes(header.encode() + body[:-10])
    with pytest.raises(ValueError, match="truncated"):
        read_ply_points(tmp_path / "c.ply")
    (tmp_path / "d.ply").write_text("solid stl\n")
    with pytest.raises(ValueError, match="not a PLY file"):
        read_ply_points(tmp_path / "d.ply")


# ----------------------------------------------------------------------------------------------------
# Geometry helpers


def test_distance_to_ground_truth_matches_brute_force():
    rng = np.random.default_rng(1)
    offset = np.array([1000.0, -2000.0, 50.0])  # far from the origin: the float32 shortcut must not lose precision
    gt = rng.uniform(-1, 1, (3000, 3)) + offset
    points = rng.uniform(-1.2, 1.2, (700, 3)) + offset
    brute = np.sqrt(((points[:, None] - gt[None]) ** 2).sum(-1))
    d, idx = distance_to_ground_truth(torch.from_numpy(points), torch.from_numpy(gt), max_block=100_000,
                                      return_index=True)  # 33 query points per block: many blocks
    np.testing.assert_allclose(d.numpy(), brute.min(axis=1), rtol=0, atol=1e-6)
    assert (idx.numpy() == brute.argmin(axis=1)).mean() > 0.99  # ties within float32 rounding may differ
    assert distance_to_ground_truth(torch.from_numpy(gt[:5]).float(), torch.from_numpy(gt).float()).max() < 1e-9
    with pytest.raises(ValueError, match=r"\[N, 3\]"):
        distance_to_ground_truth(torch.zeros(4, 2), torch.zeros(3, 3))


def test_umeyama_recovers_a_similarity():
    rng = np.random.default_rng(2)
    source = rng.normal(size=(50, 3))
    q = rng.normal(size=4)
    q /= np.linalg.norm(q)
    R = pycolmap.Rotation3d(q).matrix()  # any rotation
    target = apply_similarity(source, 2.5, R, np.array([1.0, -3.0, 0.5]))
    s, R_est, t = umeyama(source, target)
    assert s == pytest.approx(2.5) and np.allclose(R_est, R) and np.allclose(t, [1.0, -3.0, 0.5])
    s, *_ = umeyama(source, target + rng.normal(0, 0.01, target.shape))
    assert s == pytest.approx(2.5, rel=0.01)
    with pytest.raises(ValueError, match="collinear"):
        umeyama(np.outer(np.arange(5.0), [1, 2, 3]), np.outer(np.arange(5.0), [1, 2, 3]))


# ----------------------------------------------------------------------------------------------------
# Structure from motion on the stereo capture


def test_recognised_by_auto(capture):
    root, _ = capture
    assert UWBundleDataManagerConfig.can_read(root)
    assert isinstance(AutoDataManagerConfig().resolve(root), UWBundleDataManagerConfig)


def test_sfm_poses_the_capture_in_calibration_units(capture, loaded):
    root, truth = capture
    scene, _, seconds = loaded
    assert seconds < 40
    stamp = uwbundle._read_stamp(root / "sparse")
    print(f"\nSfM on {stamp['images']} images: {stamp['registered']} registered, {stamp['points']} points, "
          f"{stamp['seconds']} s; stereo check: {stamp}")
    assert stamp["registered"] >= 18 and len(scene.image_names) == stamp["registered"]  # of 20
    assert stamp["stereo_pairs_used"] >= 8
    assert stamp["stereo_rotation_error_deg"] < 0.5 and stamp["baseline_spread"] < 0.1
    # Camera centres against the truth, up to a similarity. The model was scaled by the calibrated baseline,
    # so the similarity's scale must be 1 (SfM's own scale was arbitrary). One pixel at the scene's range
    # (~3.5 m, f = 140 px) spans 2.5 cm; a registration or scaling bug shows as decimetres. Measured: scale
    # within 0.1%, RMS 3.5 mm; the bounds leave room for COLMAP's thread-order nondeterminism.
    est = denormalize_points(np.stack([c.center.double().numpy() for c in scene.cameras]), scene)
    true = np.stack([truth[name] for name in scene.image_names])
    s, R, t = umeyama(est, true)
    residual = np.linalg.norm(apply_similarity(est, s, R, t) - true, axis=1)
    assert s == pytest.approx(1.0, abs=0.02)
    assert np.sqrt((residual**2).mean()) < 0.015 and residual.max() < 0.04
    # The SfM points lie on the true surface (groundtruth.ply, 5 cm grid: up to 3.5 cm from a vertex) once
    # aligned: median distance measured 2.5 cm, against half a metre for a wrong alignment.
    assert scene.gt_points is not None and scene.gt_points.shape == (len(np.arange(-6, 6, GT_SPACING)) ** 2, 3)
    points = apply_similarity(denormalize_points(scene.points.double().numpy(), scene), s, R, t)
    d = distance_to_ground_truth(torch.from_numpy(points), scene.gt_points.double())
    assert d.median() < 0.04


def test_scene_is_undistorted_and_normalised(loaded):
    scene, _, _ = loaded
    assert scene.images.shape[1:] == (scene.cameras[0].height, scene.cameras[0].width, 3)
    assert all(name.startswith(("left/", "right/")) for name in scene.image_names)
    centres = torch.stack([c.center for c in scene.cameras]).double()
    assert centres.mean(dim=0).abs().max() < 1e-4  # centred on the cameras
    assert 0 < scene.near < 1 < scene.far  # median point distance is 1 after normalisation
    assert scene.dataset_scale > 1  # metres: the cameras are ~3.5 m from the seabed


def test_second_load_uses_the_cached_model(capture, loaded, monkeypatch):
    root, _ = capture
    _, cache, _ = loaded
    monkeypatch.setattr(uwbundle, "run_sfm", lambda *a, **k: pytest.fail("SfM ran again"))
    full, _, _ = loaded
    scene = UWBundleDataManagerConfig(cache_dir=cache).setup(data=root, downscale_factor=2).scene
    assert scene.images.shape[1:3] == (full.images.shape[1] // 2, full.images.shape[2] // 2)
    assert scene.image_names == full.image_names and scene.gt_points is not None


def test_read_only_dataset_caches_the_model_in_the_cache_dir(capture, loaded, tmp_path, monkeypatch):
    """Also the other supported layout (ROOT/images/left/, ROOT/images/right/) and the sequential matcher, whose
    steps are stereo pairs (a left and a right image are matched together and with the next steps')."""
    root, _ = capture
    copy = Path(shutil.copytree(root, tmp_path / "pool", ignore=shutil.ignore_patterns("sparse", "left", "right")))
    for side in ("left", "right"):
        shutil.copytree(root / side, copy / "images" / side)
    monkeypatch.setattr(uwbundle, "_writable", lambda folder: False)
    scene = read_uwbundle(copy, matcher="sequential", cache_dir=tmp_path / "cache", progress=False)
    assert not (copy / "sparse").exists()
    stamps = list((tmp_path / "cache" / "uwbundle").glob("pool-*/sparse/" + uwbundle.STAMP))
    stamp = uwbundle._read_stamp(stamps[0].parent)
    assert len(stamps) == 1 and len(scene.image_names) >= 18 and stamp["matcher"] == "sequential"
    assert stamp["baseline_spread"] < 0.1 and stamp["stereo_pairs_used"] >= 8
    # a user-provided model (no stamp) is used as it is, without SfM
    shutil.copytree(stamps[0].parent / "0", copy / "sparse" / "0")
    monkeypatch.setattr(uwbundle, "run_sfm", lambda *a, **k: pytest.fail("SfM ran on a dataset with a model"))
    reread = read_uwbundle(copy, matcher="sequential", cache_dir=tmp_path / "cache", progress=False)
    assert reread.image_names == scene.image_names
    # images/ + sparse/0/ is also a generic COLMAP folder: the specific datamanager wins
    assert isinstance(AutoDataManagerConfig().resolve(copy), UWBundleDataManagerConfig)


def test_a_sparse_folder_of_something_else_is_left_alone(capture, tmp_path):
    """ROOT/sparse/ that holds no model and no uw3dgs stamp (here a note) is not ours to replace: the model goes
    to the cache, whole (model and stamp together), and the folder is untouched."""
    root, _ = capture
    copy = Path(shutil.copytree(root, tmp_path / "pool", ignore=shutil.ignore_patterns("sparse")))
    (copy / "sparse").mkdir()
    (copy / "sparse" / "notes.txt").write_text("mine")
    scene = read_uwbundle(copy, cache_dir=tmp_path / "cache", progress=False)
    assert [p.name for p in (copy / "sparse").iterdir()] == ["notes.txt"]
    (cached,) = (tmp_path / "cache" / "uwbundle").glob("pool-*/sparse")
    assert sorted(p.name for p in cached.iterdir()) == ["0", uwbundle.STAMP]
    assert uwbundle._read_stamp(cached)["registered"] == len(scene.image_names)
    assert not [p for p in cached.parent.iterdir() if p.name.startswith(".")]  # no temporary folder left


def test_too_few_registered_images_is_a_clear_error(tmp_path):
    rng = np.random.default_rng(0)
    for k in range(2):
        Image.fromarray(rng.integers(0, 256, (H, W, 3), dtype=np.uint8)).save(tmp_path / f"noise{k}.png")
    with pytest.raises(SfmError, match=r"registered only 0 of 2 images") as err:
        run_sfm(tmp_path, tmp_path / "work", FixedCamera("PINHOLE", W, H, (140.0, 140.0, 80.0, 60.0)), progress=False)
    assert "overlap" in str(err.value) and "sequential matcher" in str(err.value)


def test_layout_errors(tmp_path, capture):
    root, _ = capture
    with pytest.raises(FileNotFoundError, match="no .calib"):
        read_uwbundle(tmp_path)
    shutil.copy(root / "stereo.calib", tmp_path / "rig.calib")
    with pytest.raises(FileNotFoundError, match="no left/ and right/"):
        read_uwbundle(tmp_path)
    lines = (root / "stereo.calib").read_text().splitlines()
    lines[3] = "140.0 0.0 79.3 oops"
    (tmp_path / "rig.calib").write_text("\n".join(lines))
    with pytest.raises(CalibError, match=r"rig.calib:4: 'oops' is not a number"):
        read_uwbundle(tmp_path)
    with pytest.raises(ValueError, match=r"0000.png: 160x120 pixels but its calibration is for 162x120"):
        run_sfm(root / "left", tmp_path / "w", FixedCamera("PINHOLE", W + 2, H, (1.0, 1.0, 1.0, 1.0)), progress=False)


def test_sfm_retries_a_model_that_fails_the_quality_check(capture, tmp_path, capsys):
    root, _ = capture
    names = [f"left/{k:04d}.png" for k in range(6)]
    calls = []

    def reject_first(rec: pycolmap.Reconstruction) -> tuple[float, str]:
        calls.append(rec.num_reg_images())
        return (5.0, "rejected for the test") if len(calls) == 1 else (0.5, "")

    run_sfm(root, tmp_path / "a", {"left": LEFT.fixed_camera()}, image_names=names, progress=False,
            quality_check=reject_first)
    assert len(calls) == 2

    def never_good(rec: pycolmap.Reconstruction) -> tuple[float, str]:
        calls.append(rec.num_reg_images())
        return 1.5 + len(calls), "never good"

    calls.clear()
    sparse = run_sfm(root, tmp_path / "b", {"left": LEFT.fixed_camera()}, image_names=names, progress=False,
                     quality_check=never_good, attempts=3)
    assert len(calls) == 3 and "warning: structure from motion: never good after 3 attempts" in capsys.readouterr().err
    assert pycolmap.Reconstruction(str(sparse)).num_reg_images() == calls[0]  # the least bad: the first


def test_sequential_pairs_treat_a_stereo_pair_as_one_step():
    names = [f"{side}/{k:02d}.png" for side in ("left", "right") for k in range(6)]
    pairs = set(sfm.sequential_pairs(names, 2, key=lambda name: name.split("/")[1]))
    assert ("left/00.png", "right/00.png") in pairs  # the stereo pair itself
    assert {("left/00.png", "left/01.png"), ("left/00.png", "right/02.png"), ("right/00.png", "left/01.png")} <= pairs
    assert ("left/00.png", "left/03.png") not in pairs  # 3 steps ahead: beyond overlap 2 and not a power of 2
    assert ("left/00.png", "left/04.png") not in pairs and ("left/01.png", "left/05.png") not in pairs
    plain = sfm.sequential_pairs([f"{k:02d}" for k in range(20)], 3)
    assert {b for a, b in plain if a == "00"} == {"01", "02", "03", "04"}  # 1..3, and the quadratic 1, 2, 4
