"""`uw-render`: camera paths (through the key poses, smooth between; the spiral around them), the video read back
(frame count and size), PNG frames equal to the model's own renders, and one-line errors."""

from __future__ import annotations

import dataclasses
import math
import shutil
from pathlib import Path

import imageio_ffmpeg
import numpy as np
import pytest
import torch
from conftest import as_uw3dgs, run_command, tiny_train_config, train
from PIL import Image

from uw3dgs.cli.render import entrypoint, path_cameras
from uw3dgs.engine.evaluator import load_trained
from uw3dgs.render.camera_path import (
    camera_to_world,
    interpolate_poses,
    matrix_to_quaternion,
    slerp,
    spiral_poses,
)
from uw3dgs.render.projection import quat_to_rotmat
from uw3dgs.utils.video import Mp4Writer
from uw3dgs.utils.visualize import to_uint8


@pytest.fixture(autouse=True)
def wide_terminal(monkeypatch):
    monkeypatch.setenv("COLUMNS", "300")  # rich wraps its output at the terminal width (80 under pytest)


def _train_run(root: Path, cache_dir: Path, scene, method: str) -> Path:
    """A 10-step run of `method` on the tiny scene (12 views of 48x36: test views 0000 and 0008, 10 training
    views); returns its config.yml."""
    base = tiny_train_config(root, cache_dir, scene, steps=10)
    base = dataclasses.replace(base, steps_per_save=10, steps_per_eval_image=10, steps_per_eval_all_images=10,
                               timestamp=method)
    return train(base if method == "3dgs" else as_uw3dgs(base, method)).run_dir / "config.yml"


@pytest.fixture(scope="module")
def uw_run(tmp_path_factory, cache_dir, tiny_scene_config) -> Path:
    return _train_run(tmp_path_factory.mktemp("uw"), cache_dir, tiny_scene_config, "uw3dgs")


@pytest.fixture(scope="module")
def gs_run(tmp_path_factory, cache_dir, tiny_scene_config) -> Path:
    return _train_run(tmp_path_factory.mktemp("gs"), cache_dir, tiny_scene_config, "3dgs")


def _run(argv: list[str], capsys) -> tuple[int, str]:
    """Exit status and stdout (where a command's error line goes) of uw-render."""
    code, out, _ = run_command(entrypoint, argv, capsys)
    return code, out


def _read_video(path: Path) -> tuple[dict, list[np.ndarray]]:
    reader = imageio_ffmpeg.read_frames(str(path))
    meta = next(reader)
    width, height = meta["size"]
    return meta, [np.frombuffer(frame, dtype=np.uint8).reshape(height, width, 3) for frame in reader]


def _rotation(axis: tuple[float, float, float], degrees: float) -> torch.Tensor:
    """Rotation matrix [3, 3] float64 of `degrees` about `axis` (Rodrigues)."""
    k = torch.nn.functional.normalize(torch.tensor(axis, dtype=torch.float64), dim=0)
    K = torch.tensor([[0, -k[2], k[1]], [k[2], 0, -k[0]], [-k[1], k[0], 0]], dtype=torch.float64)
    a = math.radians(degrees)
    return torch.eye(3, dtype=torch.float64) + math.sin(a) * K + (1 - math.cos(a)) * K @ K


def _pose(R: torch.Tensor, position: list[float]) -> torch.Tensor:
    pose = torch.eye(4, dtype=torch.float64)
    pose[:3, :3], pose[:3, 3] = R, torch.tensor(position, dtype=torch.float64)
    return pose


# -- camera paths --

def test_quaternions_round_trip_and_slerp_halfway():
    for axis, degrees in [((0, 0, 1), 0.0), ((1, 2, 3), 40.0), ((0, 1, 0), 179.0), ((1, 0, 0), 180.0)]:
        R = _rotation(axis, degrees)
        q = matrix_to_quaternion(R)
        assert q[0] >= 0 and abs(float(q.norm()) - 1) < 1e-12
        torch.testing.assert_close(quat_to_rotmat(q[None])[0], R, atol=1e-12, rtol=0)
    q0, q1 = matrix_to_quaternion(_rotation((1, 2, 3), 10.0)), matrix_to_quaternion(_rotation((1, 2, 3), 130.0))
    torch.testing.assert_close(quat_to_rotmat(slerp(q0, q1, 0.5)[None])[0], _rotation((1, 2, 3), 70.0),
                               atol=1e-12, rtol=0)
    # q and -q are one rotation: slerp takes the shorter arc either way
    torch.testing.assert_close(quat_to_rotmat(slerp(q0, -q1, 0.25)[None])[0], _rotation((1, 2, 3), 40.0),
                               atol=1e-12, rtol=0)


def test_interpolated_path_passes_through_the_keys_and_is_smooth_between():
    up = (0.2, -1.0, 0.1)
    keys = torch.stack([_pose(_rotation(up, 0.0), [0, 0, 0]), _pose(_rotation(up, 90.0), [1, 0, 0]),
                        _pose(_rotation(up, 120.0), [3, 1, 0]), _pose(_rotation((1, 0, 0), 30.0), [3.5, 1, 2])])
    n = 4
    path = interpolate_poses(keys, n)
    assert path.shape == (3 * n + 1, 4, 4)
    for k in range(len(keys)):
        torch.testing.assert_close(path[k * n], keys[k], atol=1e-6, rtol=0)
    # halfway between two keys: the rotation halfway along the arc between them
    torch.testing.assert_close(path[n // 2, :3, :3], _rotation(up, 45.0), atol=1e-12, rtol=0)
    torch.testing.assert_close(path[n + n // 2, :3, :3], _rotation(up, 105.0), atol=1e-12, rtol=0)
    assert all(abs(float(torch.linalg.det(pose[:3, :3])) - 1) < 1e-12 for pose in path)
    # evenly spaced keys on a line: the spline is that line, travelled at constant speed
    line = torch.stack([_pose(torch.eye(3, dtype=torch.float64), [2.0 * k, -k, 0.5 * k]) for k in range(4)])
    steps = interpolate_poses(line, 5)[:, :3, 3]
    torch.testing.assert_close(steps, torch.linspace(0, 3, 16, dtype=torch.float64)[:, None]
                               * torch.tensor([2.0, -1.0, 0.5], dtype=torch.float64), atol=1e-12, rtol=0)
    # unevenly spaced keys: the velocity still has no jump at a key (a piecewise-linear path would have one)
    fine = 1000
    p = interpolate_poses(keys, fine)[:, :3, 3]
    for k in (1, 2):
        before, after = p[k * fine] - p[k * fine - 1], p[k * fine + 1] - p[k * fine]
        assert float((after - before).norm()) < 1e-2 * float(after.norm())


def test_spiral_stays_at_the_training_cameras_distance_and_height():
    """Forward-looking cameras tilted down at a patch of surface (a dive): the spiral's cameras keep their
    distances to the scene centre (the focus) and their heights above it."""
    from uw3dgs.render.camera_path import look_at

    generator = torch.Generator().manual_seed(0)
    points = torch.rand(500, 3, generator=generator, dtype=torch.float64) * torch.tensor([4.0, 4.0, 0.2])
    target = torch.tensor([2.0, 2.0, 0.0], dtype=torch.float64)
    keys = torch.stack([look_at(torch.tensor([0.5 * k, -1.0 + 0.1 * k, 2.0 + 0.2 * (k % 3)], dtype=torch.float64),
                                target, torch.tensor([0.0, 0.0, -1.0], dtype=torch.float64)) for k in range(8)])
    spiral = spiral_poses(keys, points, 36)
    centres, axes = spiral[:, :3, 3], spiral[:, :3, 2]
    projector = torch.eye(3, dtype=torch.float64) - axes[:, :, None] * axes[:, None, :]
    focus = torch.linalg.solve(projector.sum(0), (projector @ centres[..., None]).sum(0))[:, 0]
    reach, distances = (keys[:, :3, 3] - focus).norm(dim=-1), (centres - focus).norm(dim=-1)
    assert float(distances.min()) >= float(reach.min()) - 1e-9 and float(distances.max()) <= float(reach.max()) + 1e-9
    up = -keys[:, :3, 1].mean(0)
    up = up / up.norm()
    heights, key_heights = (centres - focus) @ up, (keys[:, :3, 3] - focus) @ up
    assert float(heights.min()) >= float(key_heights.min()) - 1e-6


def test_interpolate_and_spiral_cameras_of_a_run(uw_run):
    _, datamanager, _, _ = load_trained(uw_run)
    train = [datamanager.scene.cameras[i] for i in datamanager.train_indices]
    cameras, files = path_cameras("interpolate", datamanager, frames_per_view=3, num_frames=1)
    assert len(cameras) == 3 * (len(train) - 1) + 1 and files[0] == "frame_00000.png"
    for k, key in enumerate(train):  # the training views themselves, intrinsics of the first
        torch.testing.assert_close(cameras[3 * k].viewmat, key.viewmat, atol=1e-6, rtol=0)
        torch.testing.assert_close(cameras[3 * k].center, key.center, atol=1e-5, rtol=0)
        assert torch.equal(cameras[3 * k].K, train[0].K) and cameras[3 * k].width == train[0].width
    keys = torch.stack([camera_to_world(camera) for camera in train])
    spiral = spiral_poses(keys, datamanager.scene.points, 24)
    assert len(spiral) == 24
    centres, axes = spiral[:, :3, 3], spiral[:, :3, 2]
    # every optical axis passes through one point (the focus): least squares, then the distances to it
    projector = torch.eye(3, dtype=torch.float64) - axes[:, :, None] * axes[:, None, :]
    focus = torch.linalg.solve(projector.sum(0), (projector @ centres[..., None]).sum(0))[:, 0]
    assert float((projector @ (focus - centres)[..., None]).norm(dim=1).max()) < 1e-9
    assert bool((((focus - centres) * axes).sum(-1) > 0).all())  # in front of every camera
    spread = (centres - centres.mean(0)).norm(dim=-1)
    assert float(spread.min()) > 0  # it moves around the mean pose ...
    assert float(spread.max()) <= float((keys[:, :3, 3] - keys[:, :3, 3].mean(0)).norm(dim=-1).max()) * 2  # near it
    # ... at the training cameras' own distances to the scene centre (the focus): no close-ups, nothing beyond
    reach = (keys[:, :3, 3] - focus).norm(dim=-1)
    distances = (centres - focus).norm(dim=-1)
    assert float(distances.min()) >= float(reach.min()) - 1e-9 and float(distances.max()) <= float(reach.max()) + 1e-9


# -- frames and video --

def test_video_has_one_frame_per_pose_of_the_frames_size(uw_run, tmp_path, capsys):
    video, frames = tmp_path / "v.mp4", tmp_path / "frames"
    code, text = _run([str(uw_run), "--frames-per-view", "2", "--output", str(video), "--images", str(frames)],
                      capsys)
    assert code == 0, text
    pngs = sorted(frames.iterdir())
    assert len(pngs) == 2 * (10 - 1) + 1  # 10 training views, 2 frames from one to the next
    first = np.asarray(Image.open(pngs[0]))
    height, width = first.shape[:2]
    assert width == 3 * 48 + 2 * 2 and height > 36  # uwi, uri, depth with separators, labels above them
    meta, decoded = _read_video(video)
    assert len(decoded) == len(pngs) and meta["fps"] == 24
    assert meta["size"] == (width + width % 2, height + height % 2)
    # the frames are the rendered ones (up to H.264's loss), in order
    assert np.abs(decoded[0][:height, :width].astype(float) - first).mean() < 8
    assert np.abs(decoded[-1][:height, :width].astype(float) - np.asarray(Image.open(pngs[-1]))).mean() < 8
    # odd sides (9 x 7 at --downscale 5) are padded to even, as H.264 in yuv420p needs
    code, text = _run([str(uw_run), "--path", "spiral", "--num-frames", "6", "--outputs", "uri", "--downscale", "5",
                       "--output", str(tmp_path / "small.mp4")], capsys)
    assert code == 0, text
    meta, decoded = _read_video(tmp_path / "small.mp4")
    assert meta["size"] == (10, 8) and len(decoded) == 6


def test_test_view_pngs_are_the_models_renders(uw_run, tmp_path, capsys):
    out = tmp_path / "uri"
    code, text = _run([str(uw_run), "--path", "test", "--outputs", "uri", "--images", str(out)], capsys)
    assert code == 0, text
    assert sorted(p.name for p in out.iterdir()) == ["0000.png", "0008.png"]  # named after the test views
    assert not (uw_run.parent / "render").exists()  # --images alone: no video
    _, datamanager, model, _ = load_trained(uw_run)
    model.eval()
    with torch.no_grad():
        renders = {datamanager.scene.image_names[i]: model.get_outputs(datamanager.cameras[i])
                   for i in datamanager.test_indices}
    for name, outputs in renders.items():
        assert np.array_equal(np.asarray(Image.open(out / name)), to_uint8(outputs["uri"].clamp(0, 1))), name
    # two outputs: labelled above, the images themselves untouched below
    both = tmp_path / "both"
    code, text = _run([str(uw_run), "--path", "test", "--outputs", "uwi,uri", "--images", str(both)], capsys)
    assert code == 0, text
    frame = np.asarray(Image.open(both / "0008.png"))
    outputs = renders["0008.png"]
    assert frame.shape[0] > 36 and frame[:-36].any()  # a label strip, with text in it
    assert np.array_equal(frame[-36:, :48], to_uint8(outputs["rgb"].clamp(0, 1)))
    assert np.array_equal(frame[-36:, 50:], to_uint8(outputs["uri"].clamp(0, 1)))


def test_3dgs_defaults_to_what_it_renders(gs_run, capsys):
    code, text = _run([str(gs_run), "--frames-per-view", "1"], capsys)
    assert code == 0, text
    meta, decoded = _read_video(gs_run.parent / "render" / "interpolate.mp4")
    assert len(decoded) == 10 and meta["size"][0] == 2 * 48 + 2  # uwi and depth: the method has no URI


def test_an_interrupted_video_leaves_the_old_file(tmp_path):
    video = tmp_path / "v.mp4"
    video.write_bytes(b"old")
    with pytest.raises(KeyboardInterrupt), Mp4Writer(video, fps=24) as writer:
        writer.write(np.zeros((8, 8, 3), dtype=np.uint8))
        raise KeyboardInterrupt
    assert video.read_bytes() == b"old" and sorted(p.name for p in tmp_path.iterdir()) == ["v.mp4"]


# -- errors --

def _error(argv: list[str], capsys) -> str:
    code, text = _run(argv, capsys)
    assert code == 2 and len(text.strip().splitlines()) == 1, text
    assert text.startswith("error: ")
    return text


def test_bad_input_is_one_line(gs_run, tmp_path, capsys):
    text = _error([str(gs_run), "--outputs", "uwi,uri"], capsys)
    assert "3dgs run renders no uri" in text and "it can render uwi, depth" in text
    text = _error([str(gs_run), "--outputs", "uwi,range"], capsys)
    assert "unknown output range" in text and "uwi, uri, depth, attenuation, backscatter" in text
    text = _error([str(gs_run), "--path", "orbit"], capsys)
    assert "--path orbit" in text and "test, train, interpolate, spiral" in text
    text = _error([str(gs_run), "--output", str(tmp_path / "v.avi")], capsys)
    assert ".mp4" in text and "--images" in text
    blocker = tmp_path / "file"
    blocker.write_text("")
    text = _error([str(gs_run), "--output", str(blocker / "v.mp4")], capsys)
    assert f"--output {blocker / 'v.mp4'}" in text and "is a file, not a folder" in text
    (tmp_path / "dir.mp4").mkdir()
    text = _error([str(gs_run), "--output", str(tmp_path / "dir.mp4")], capsys)
    assert "is a folder" in text
    text = _error([str(gs_run), "--images", str(blocker)], capsys)
    assert "--images" in text and "is a file" in text
    untrained = tmp_path / "untrained"
    untrained.mkdir()
    shutil.copy(gs_run, untrained / "config.yml")
    text = _error([str(untrained / "config.yml"), "--output", str(tmp_path / "v.mp4")], capsys)
    assert "no checkpoint" in text and "train it first" in text
    assert not (tmp_path / "v.mp4").exists() and not list(tmp_path.glob(".*.tmp"))
