"""The nerfstudio datamanager (transforms.json): a COLMAP model converted as nerfstudio's ns-process-data does
(OpenGL camera axes, world axes swapped) reads back as the same cameras as the COLMAP reading; the split the file
carries; initial points from ply_file_path or random ones; bad input; a plain image folder's error; a short run."""

from __future__ import annotations

import dataclasses
import json
import shutil
from pathlib import Path

import numpy as np
import pycolmap
import pytest
from test_datamanagers import CAMERA_PARAMS, HEIGHT, WIDTH, make_dataset

from uw3dgs.data.colmap_dataset import DatasetError
from uw3dgs.data.datamanager import AutoDataManagerConfig
from uw3dgs.datamanagers.colmap import ColmapDataManagerConfig
from uw3dgs.datamanagers.nerfstudio import NerfstudioDataManagerConfig
from uw3dgs.datamanagers.transforms_json import read_transforms
from uw3dgs.engine.trainer import Trainer
from uw3dgs.methods.gaussian_splatting import method as gaussian_splatting

TRAIN_STEPS = 100
NS_WORLD = np.array([[1.0, 0, 0, 0], [0, 0, 1, 0], [0, -1, 0, 0], [0, 0, 0, 1]])
"""nerfstudio's colmap_to_json world change (rows 0, 2, 1 of the identity, then row 2 negated)."""


def colmap_to_transforms(root: Path, world: np.ndarray, ply: bool = True, split: dict | None = None) -> Path:
    """ROOT/transforms.json from ROOT/sparse/0 as nerfstudio writes it, independently of uw3dgs' reader: each pose
    inverted, its camera's y and z axes negated (OpenCV -> OpenGL), then `world` applied; per-frame intrinsics
    (the top level holds none); points through `world` into sparse_pc.ply with colours."""
    rec = pycolmap.Reconstruction(str(root / "sparse" / "0"))
    frames = []
    for image in sorted(rec.images.values(), key=lambda im: im.name):
        w2c = np.eye(4)
        w2c[:3] = image.cam_from_world().matrix()
        c2w = np.linalg.inv(w2c)
        c2w[0:3, 1:3] *= -1
        c2w = world @ c2w
        cam = rec.cameras[image.camera_id]
        fx, fy, cx, cy, k1, k2, p1, p2 = [*cam.params, 0.0, 0.0, 0.0, 0.0][:8]  # OPENCV, or PINHOLE
        frames.append({"file_path": f"images/{image.name}", "transform_matrix": c2w.tolist(), "fl_x": fx,
                       "fl_y": fy, "cx": cx, "cy": cy, "w": cam.width, "h": cam.height, "k1": k1, "k2": k2,
                       "p1": p1, "p2": p2, "camera_model": "OPENCV"})
    meta = {"frames": frames, "applied_transform": world[:3].tolist(), **(split or {})}
    if ply:
        ids = sorted(rec.points3D)
        xyz = np.array([rec.points3D[i].xyz for i in ids]) @ world[:3, :3].T + world[:3, 3]
        rgb = np.array([rec.points3D[i].color for i in ids])
        header = (f"ply\nformat ascii 1.0\nelement vertex {len(ids)}\nproperty float x\nproperty float y\n"
                  "property float z\nproperty uint8 red\nproperty uint8 green\nproperty uint8 blue\nend_header\n")
        rows = "".join(f"{x} {y} {z} {r} {g} {b}\n" for (x, y, z), (r, g, b) in zip(xyz, rgb, strict=True))
        (root / "sparse_pc.ply").write_text(header + rows)
        meta["ply_file_path"] = "sparse_pc.ply"
    (root / "transforms.json").write_text(json.dumps(meta))
    return root


def _both(tmp_path, world=NS_WORLD, **kwargs):
    root = colmap_to_transforms(make_dataset(tmp_path / "data", model="OPENCV"), world, **kwargs)
    colmap = ColmapDataManagerConfig(llffhold=2, cache_dir=tmp_path / "cache").setup(data=root, downscale_factor=2)
    ns = NerfstudioDataManagerConfig(llffhold=2, cache_dir=tmp_path / "cache").setup(data=root, downscale_factor=2)
    return colmap, ns


@pytest.mark.parametrize("world", [np.eye(4), NS_WORLD], ids=["same-world", "nerfstudio-world"])
def test_transforms_json_cameras_agree_with_the_colmap_reading(tmp_path, world):
    colmap, ns = _both(tmp_path, world)
    assert ns.scene.image_names == colmap.scene.image_names == [f"{k:04d}.png" for k in range(4)]
    np.testing.assert_array_equal(ns.scene.images.numpy(), colmap.scene.images.numpy())  # same undistortion
    assert ns.scene.dataset_scale == pytest.approx(colmap.scene.dataset_scale, rel=1e-9)
    assert (ns.scene.near, ns.scene.far) == pytest.approx((colmap.scene.near, colmap.scene.far), rel=1e-6)
    rotation = world[:3, :3]
    for a, b in zip(ns.scene.cameras, colmap.scene.cameras, strict=True):
        assert (a.width, a.height) == (b.width, b.height)
        np.testing.assert_allclose(a.K.numpy(), b.K.numpy(), rtol=1e-6)
        # after normalisation the poses differ by the world rotation only: R_ns = R_colmap @ world^T, same t
        np.testing.assert_allclose(a.viewmat[:3, :3].double().numpy(), b.viewmat[:3, :3].double().numpy()
                                   @ rotation.T, atol=1e-6)
        np.testing.assert_allclose(a.viewmat[:3, 3].numpy(), b.viewmat[:3, 3].numpy(), atol=1e-5)
    np.testing.assert_allclose(ns.scene.points.numpy(), colmap.scene.points.numpy() @ rotation.T, atol=1e-5)
    np.testing.assert_allclose(ns.scene.point_colors.numpy(), colmap.scene.point_colors.numpy())
    assert (ns.train_indices, ns.test_indices) == (colmap.train_indices, colmap.test_indices) == ([1, 3], [0, 2])


def test_the_split_the_file_carries_is_used(tmp_path):
    split = {"train_filenames": ["images/0000.png", "images/0001.png", "images/0002.png"],
             "val_filenames": ["images/0003.png"]}
    _, ns = _both(tmp_path, split=split)
    assert (ns.train_indices, ns.test_indices) == ([0, 1, 2], [3])
    split["test_filenames"] = ["images/0000.png"]
    split["train_filenames"] = split["train_filenames"][1:]
    (tmp_path / "data" / "transforms.json").unlink()
    colmap_to_transforms(tmp_path / "data", NS_WORLD, split=split)
    dm = NerfstudioDataManagerConfig(cache_dir=tmp_path / "cache").setup(data=tmp_path / "data")
    assert (dm.train_indices, dm.test_indices) == ([1, 2], [0])  # test_filenames wins over val_filenames
    by_hold = NerfstudioDataManagerConfig(llffhold=2, split="llffhold", cache_dir=tmp_path / "cache")
    assert by_hold.setup(data=tmp_path / "data").test_indices == [0, 2]


def test_without_points_random_ones_inside_the_cameras_bounds(tmp_path, capsys):
    root = colmap_to_transforms(make_dataset(tmp_path / "data", model="PINHOLE"), NS_WORLD, ply=False)
    dm = NerfstudioDataManagerConfig(cache_dir=tmp_path / "cache", random_points=500, normalize=False).setup(
        data=root)
    assert "no ply_file_path" in capsys.readouterr().err
    centers = np.stack([c.center.numpy() for c in dm.scene.cameras])
    middle = centers.mean(axis=0)
    half = np.linalg.norm(centers - middle, axis=1).max()
    points = dm.scene.points.numpy()
    assert points.shape == (500, 3) and np.abs(points - middle).max() <= half * (1 + 1e-5)
    assert 0 < dm.scene.near < dm.scene.far


def test_instant_ngp_style_file_with_top_level_intrinsics(tmp_path):
    """camera_angle_x and no size: the focal length from the angle, the size from the images."""
    root = make_dataset(tmp_path / "data", model="PINHOLE")
    fx = CAMERA_PARAMS["PINHOLE"][0]
    frames = [{"file_path": f"images/{k:04d}", "transform_matrix": np.eye(4).tolist()} for k in range(4)]
    for k, frame in enumerate(frames):
        frame["transform_matrix"][0][3] = 0.3 * k
    meta = {"camera_angle_x": 2 * np.arctan(0.5 * WIDTH / fx), "frames": frames}
    (root / "transforms.json").write_text(json.dumps(meta))
    dm = NerfstudioDataManagerConfig(cache_dir=tmp_path / "cache", random_points=100).setup(data=root)
    K = dm.scene.cameras[0].K.numpy()
    assert K[0, 0] == pytest.approx(fx) and K[1, 1] == pytest.approx(fx)
    assert (K[0, 2], K[1, 2]) == pytest.approx((WIDTH / 2, HEIGHT / 2))
    # an identity OpenGL pose looks down -z: the OpenCV camera's z axis is the world's -z
    np.testing.assert_allclose(dm.scene.cameras[0].viewmat[2, :3].numpy(), [0, 0, -1], atol=1e-6)


@pytest.mark.parametrize("change, fragment", [
    (lambda meta: meta["frames"][0].update(camera_model="OPENCV_FISHEYE"), "OPENCV_FISHEYE"),
    (lambda meta: meta["frames"][1].update(k3=0.01), "k3"),
    (lambda meta: meta["frames"][0].pop("transform_matrix"), "transform_matrix"),
    (lambda meta: meta.update(train_filenames=["images/nope.png"]), "nope.png"),
])
def test_bad_transforms_json_is_named(tmp_path, change, fragment):
    root = colmap_to_transforms(make_dataset(tmp_path / "data"), NS_WORLD)
    meta = json.loads((root / "transforms.json").read_text())
    change(meta)
    (root / "transforms.json").write_text(json.dumps(meta))
    with pytest.raises((DatasetError, FileNotFoundError)) as info:
        NerfstudioDataManagerConfig(cache_dir=tmp_path / "cache").setup(data=root)
    assert fragment in str(info.value) and "\n" not in str(info.value)


def test_frames_whose_images_are_missing_are_skipped_with_a_warning(tmp_path, capsys):
    """instant-ngp's fox lists 67 frames and ships 50 images: the frames without an image are left out, named in
    one warning; a file none of whose images exists is an error naming it."""
    root = colmap_to_transforms(make_dataset(tmp_path / "data"), NS_WORLD)
    meta = json.loads((root / "transforms.json").read_text())
    frames = len(meta["frames"])
    meta["frames"][2]["file_path"] = "images/gone.png"
    (root / "transforms.json").write_text(json.dumps(meta))
    scene = read_transforms(root)
    assert len(scene.model.names) == frames - 1 and "gone.png" not in " ".join(scene.model.names)
    err = capsys.readouterr().err
    assert f"1 of its {frames} frames" in err and "gone.png" in err
    for frame in meta["frames"]:
        frame["file_path"] = "images/gone.png"
    (root / "transforms.json").write_text(json.dumps(meta))
    with pytest.raises(FileNotFoundError, match="none of its .* frames' images exists"):
        read_transforms(root)


def test_a_plain_image_folder_is_told_to_run_process_data(tmp_path):
    root = make_dataset(tmp_path / "data")
    shutil.rmtree(root / "sparse")
    for folder in (root, root / "images"):
        with pytest.raises(ValueError) as info:
            AutoDataManagerConfig().resolve(folder)
        assert f"uw-process-data --images {root / 'images'}" in str(info.value) and "\n" not in str(info.value)


def test_auto_picks_nerfstudio_for_a_transforms_json_folder(tmp_path):
    root = colmap_to_transforms(make_dataset(tmp_path / "data"), NS_WORLD)
    shutil.rmtree(root / "sparse")
    assert type(AutoDataManagerConfig().resolve(root)) is NerfstudioDataManagerConfig


@pytest.mark.slow
def test_uw_train_trains_on_a_transforms_json_folder(tmp_path):
    """The synthetic scene written by uw-synth, converted to transforms.json: a short 3DGS run learns it."""
    from uw3dgs.datamanagers.synthetic.cli import entrypoint as uw_synth

    root = tmp_path / "scene"
    uw_synth(["--out", str(root), "--width", "48", "--height", "36", "--num-views", "8"])
    (root / "Images_wb").rename(root / "images")
    colmap_to_transforms(root, NS_WORLD)
    for path in ("sparse", "gt", "poses_bounds.npy"):
        target = root / path
        if target.is_dir():
            shutil.rmtree(target)
        elif target.exists():
            target.unlink()
    config = dataclasses.replace(
        gaussian_splatting.config, data=root, max_num_iterations=TRAIN_STEPS, output_dir=tmp_path / "out",
        progress=False, device="cpu", timestamp="t", steps_per_save=10**6, steps_per_eval_image=10**6,
        steps_per_eval_all_images=10**6)  # the datamanager picked from --data, as `uw-train 3dgs --data DIR` does
    trainer = Trainer(config)
    trainer.setup()
    assert type(trainer.datamanager.config) is NerfstudioDataManagerConfig
    first = trainer.eval_all(0)["psnr"]
    trainer.train()
    last = trainer.eval_all(TRAIN_STEPS)["psnr"]
    # wrong poses (a convention mixed up) start far lower and do not learn the views
    assert last > 25.0 and last > first + 2.0, (first, last)
