"""`uw-process-data`: a folder of a user's underwater images (here: the synthetic scene's rendered views, whose
true poses are known) becomes a COLMAP dataset that the `colmap` datamanager reads as it is."""

from __future__ import annotations

import stat
import sys
from pathlib import Path

import numpy as np
import pycolmap
import pytest
from conftest import run_command
from PIL import Image

from uw3dgs.cli.process_data import entrypoint
from uw3dgs.data.colmap_dataset import denormalize_points
from uw3dgs.data.datamanager import AutoDataManagerConfig
from uw3dgs.datamanagers.colmap import ColmapDataManagerConfig
from uw3dgs.datamanagers.synthetic.config import SyntheticSceneConfig
from uw3dgs.datamanagers.synthetic.scene import generate_scene
from uw3dgs.datamanagers.uwbundle import apply_similarity, umeyama

# 12 views of a forward pass at 160x120, looking 20 degrees ahead of straight down (see test_uwbundle.py on
# why not the default 35 degrees at this tiny size). Self-calibration (OPENCV) registered all 12 views in
# 3 of 3 runs for each of two seeds, camera centres within 2-5 mm RMS of the truth.
SCENE = SyntheticSceneConfig(width=160, height=120, num_views=12, terrain_size=12.0, path_length=3.0, num_points=100,
                             tilt_deg=20.0)


@pytest.fixture(scope="module")
def scene_dir(tmp_path_factory) -> Path:
    return generate_scene(SCENE, tmp_path_factory.mktemp("photos") / "scene", progress=False)


@pytest.fixture(autouse=True)
def wide_terminal(monkeypatch):
    monkeypatch.setenv("COLUMNS", "300")  # rich wraps its output at the terminal width (80 under pytest)


def _true_centres(scene_dir: Path) -> dict[str, np.ndarray]:
    rec = pycolmap.Reconstruction(str(scene_dir / "sparse" / "0"))
    return {im.name: im.projection_center() for im in rec.images.values()}


def _run(argv: list[str], capsys) -> tuple[int, str]:
    code, out, err = run_command(entrypoint, argv, capsys)
    return code, out + err


def test_photos_become_a_colmap_dataset(scene_dir, tmp_path, capsys):
    out = tmp_path / "reef"
    code, text = _run(["--images", str(scene_dir / "Images_wb"), "--out", str(out), "--threads", "2"], capsys)
    assert code == 0, text
    assert "12 of 12 registered" in text and "exhaustive" in text and f"uw-train uw3dgs --data {out}" in text
    # sized to the machine: 160x120 images train at full size in the default 30 minutes on a CPU
    assert "--downscale-factor 1 --max-num-iterations 6000" in text and "minutes of training" in text
    assert sorted(p.name for p in (out / "images").iterdir()) == [f"{k:04d}.png" for k in range(12)]
    rec = pycolmap.Reconstruction(str(out / "sparse" / "0"))
    assert {c.model_name for c in rec.cameras.values()} == {"PINHOLE"}  # undistorted
    assert (out / "colmap" / "database.db").is_file()
    # The colmap datamanager reads the folder as it is, and 'auto' picks it.
    assert isinstance(AutoDataManagerConfig().resolve(out), ColmapDataManagerConfig)
    scene = ColmapDataManagerConfig(cache_dir=tmp_path / "cache").setup(data=out).scene
    assert len(scene.image_names) == 12 and scene.images.shape[1:] == (scene.cameras[0].height,
                                                                      scene.cameras[0].width, 3)
    # Poses against the truth up to a similarity: one pixel at the seabed (~3.2 m, f = 139 px) spans 2.3 cm;
    # measured 2-5 mm RMS.
    truth = _true_centres(scene_dir)
    est = denormalize_points(np.stack([c.center.double().numpy() for c in scene.cameras]), scene)
    true = np.stack([truth[name] for name in scene.image_names])
    s, R, t = umeyama(est, true)
    residual = np.linalg.norm(apply_similarity(est, s, R, t) - true, axis=1)
    assert np.sqrt((residual**2).mean()) < 0.015


def test_every_n_max_size_and_known_intrinsics(scene_dir, tmp_path, capsys):
    out = tmp_path / "small"
    f = 0.5 * 144 / np.tan(np.radians(SCENE.fov_deg / 2))  # the true focal length at 144x108
    argv = ["--images", str(scene_dir / "Images_wb"), "--out", str(out), "--every-n", "2", "--max-size", "144",
            "--camera-model", "PINHOLE", "--camera-params", f"{f},{f},72,54", "--matcher", "sequential"]
    code, text = _run(argv, capsys)
    assert code == 0, text
    assert "6 of 6 registered" in text and "(fixed)" in text and "sequential" in text
    names = sorted(p.name for p in (out / "images").iterdir())
    assert names == [f"{k:04d}.png" for k in range(0, 12, 2)]
    assert all(Image.open(out / "images" / n).size == (144, 108) for n in names)
    camera = next(iter(pycolmap.Reconstruction(str(out / "sparse" / "0")).cameras.values()))
    np.testing.assert_allclose(camera.params, [f, f, 72, 54])  # fixed: not refined


def test_too_few_registered_images_is_a_clear_error(tmp_path, capsys):
    photos = tmp_path / "murk"
    photos.mkdir()
    rng = np.random.default_rng(0)
    for k in range(3):
        Image.fromarray(rng.integers(0, 256, (90, 120, 3), dtype=np.uint8)).save(photos / f"{k}.jpg")
    out = tmp_path / "out"
    code, text = _run(["--images", str(photos), "--out", str(out)], capsys)
    assert code == 2
    assert "registered only 0 of 3 images" in text
    assert "overlap" in text
    assert out.is_dir() and not any(out.iterdir())  # left empty: the same command can run again
    assert sorted(p.name for p in tmp_path.iterdir()) == ["murk", "out"]  # and no half-written dataset beside it


def test_argument_errors(scene_dir, tmp_path, capsys):
    code, text = _run(["--out", str(tmp_path / "a")], capsys)
    assert code == 2 and "exactly one of --images DIR and --video FILE" in text
    full = tmp_path / "full"
    full.mkdir()
    (full / "x.txt").write_text("mine")
    code, text = _run(["--images", str(scene_dir / "Images_wb"), "--out", str(full)], capsys)
    assert code == 2 and "not an empty folder" in text and (full / "x.txt").read_text() == "mine"
    code, text = _run(["--images", str(scene_dir / "Images_wb"), "--out", str(tmp_path / "b"),
                       "--camera-params", "1,2"], capsys)
    assert code == 2 and "takes 8 parameters, got 2" in text
    code, text = _run(["--images", str(scene_dir / "Images_wb"), "--out", str(tmp_path / "c"), "--threads", "0"],
                      capsys)
    assert code == 2 and "--threads must be -1" in text


def test_video_without_ffmpeg_says_what_to_do(tmp_path, capsys, monkeypatch):
    import imageio_ffmpeg

    def no_binary():  # as on a platform imageio-ffmpeg ships no binary for, with no ffmpeg installed
        raise RuntimeError("No ffmpeg exe could be found")

    monkeypatch.setattr(imageio_ffmpeg, "get_ffmpeg_exe", no_binary)
    code, text = _run(["--video", str(tmp_path / "dive.mp4"), "--every-n", "10", "--out", str(tmp_path / "o")],
                      capsys)
    assert code == 2 and "no ffmpeg program found" in text and "-fps_mode vfr" in text and "--images" in text


def test_video_frames_are_decoded_by_the_bundled_ffmpeg(tmp_path):
    """A real H.264 video (written by uw-render's writer) decoded by imageio-ffmpeg's ffmpeg: frames 0, 5, 10 of
    12, each recognised by its grey level."""
    from uw3dgs.cli.process_data import extract_video_frames
    from uw3dgs.utils.video import Mp4Writer

    levels = [20 * k for k in range(12)]
    with Mp4Writer(tmp_path / "dive.mp4", fps=30) as video:
        for level in levels:
            video.write(np.full((48, 64, 3), level, dtype=np.uint8))
    names = extract_video_frames(tmp_path / "dive.mp4", 5, tmp_path / "frames")
    assert names == ["frame_00001.png", "frame_00002.png", "frame_00003.png"]
    for name, level in zip(names, levels[::5], strict=True):
        pixels = np.asarray(Image.open(tmp_path / "frames" / name), dtype=np.float64)
        assert pixels.shape == (48, 64, 3) and abs(pixels.mean() - level) < 3, (name, pixels.mean(), level)


def test_video_frames_come_from_ffmpeg(scene_dir, tmp_path, capsys, monkeypatch):
    """A stand-in ffmpeg (named by IMAGEIO_FFMPEG_EXE, which imageio-ffmpeg honours first) that 'decodes' a list
    of image files, honouring the select filter: checks the command line uw-process-data builds and the rest of
    the pipeline on the exact images (a real video's compression would blur them)."""
    bin_dir = tmp_path / "bin"
    bin_dir.mkdir()
    fake = bin_dir / "ffmpeg"
    fake.write_text(f"""#!{sys.executable}
import re, shutil, sys
args = sys.argv[1:]
frames = open(args[args.index("-i") + 1]).read().split()
n = int(re.fullmatch(r"select=not\\(mod\\(n\\\\,(\\d+)\\)\\)", args[args.index("-vf") + 1]).group(1))
assert args[args.index("-fps_mode") + 1] == "vfr"
for k, frame in enumerate(frames[::n]):
    shutil.copy(frame, args[-1] % (k + 1))
""")
    fake.chmod(fake.stat().st_mode | stat.S_IXUSR)
    monkeypatch.setenv("IMAGEIO_FFMPEG_EXE", str(fake))
    video = tmp_path / "dive.mp4"
    video.write_text("\n".join(str(p) for p in sorted((scene_dir / "Images_wb").glob("*.png"))))
    out = tmp_path / "video"
    code, text = _run(["--video", str(video), "--every-n", "1", "--out", str(out)], capsys)
    assert code == 0, text
    assert "12 of 12 registered (sequential matching)" in text
    assert sorted(p.name for p in (out / "images").iterdir()) == [f"frame_{k:05d}.png" for k in range(1, 13)]
