"""`uw-process-data --images DIR --out DIR`: your own underwater photos (or video frames) -> a COLMAP dataset.

    uw-process-data --images dive/photos --out data/my-reef
    uw-process-data --images dive/frames --out data/my-reef --every-n 10 --matcher sequential
    uw-process-data --video dive.mp4 --every-n 10 --out data/my-reef

Writes OUT/images/ and OUT/sparse/0/ (undistorted PINHOLE cameras, by COLMAP's undistorter), which the
`colmap` datamanager reads as it is: `uw-train uw3dgs --data OUT`. OUT/colmap/ keeps the feature database
and the distorted model. Video is decoded by the ffmpeg program that the imageio-ffmpeg package ships (a
dependency of uw3dgs; IMAGEIO_FFMPEG_EXE names another, version 5.1 or later), so no system ffmpeg is needed.
The dataset is assembled beside OUT and renamed into place when complete: a failed or killed run leaves OUT as
it was (empty), so the same command can simply be run again.
"""

from __future__ import annotations

import shutil
import subprocess
import tempfile
import time
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Literal

import numpy as np
import pycolmap
import torch
import tyro
from PIL import Image
from rich.console import Console
from rich.progress import Progress
from rich.table import Table

from uw3dgs.cli.errors import exit_with_error
from uw3dgs.data.sfm import FixedCamera, SfmError, list_images, quiet_colmap, run_sfm
from uw3dgs.engine.run_size import StepCost, size_run, suggestion
from uw3dgs.utils.console import warn
from uw3dgs.utils.images import image_size
from uw3dgs.utils.io import atomic_folder
from uw3dgs.utils.video import ffmpeg_executable


@dataclass(frozen=True)
class ProcessDataArgs:
    """Turn a folder of underwater photos (or every n-th frame of a video) into a COLMAP dataset for uw-train.

    Structure from motion (pycolmap: SIFT on the CPU, matching, incremental mapping) poses the images; COLMAP's
    undistorter then writes OUT/images/ and OUT/sparse/0/ (PINHOLE), which `uw-train METHOD --data OUT` reads.
    Video is decoded by the ffmpeg program bundled with the imageio-ffmpeg package (no system ffmpeg needed);
    frames extracted otherwise can be passed as a folder with --images. Self-calibration of a
    near-flat seabed can get the focal length wrong; if you know the intrinsics (a calibration in water),
    pass them with --camera-params: they are then kept fixed. See docs/uwbundle.md.
    """

    out: Path
    """Output folder, new or empty: images/, sparse/0/, and colmap/ (feature database, distorted model)."""
    images: Path | None = None
    """Folder of photos or extracted video frames (PNG, JPEG, TIFF, BMP; subfolders too), used in name order."""
    video: Path | None = None
    """A video file, instead of --images; decoded by the ffmpeg program bundled with imageio-ffmpeg."""
    every_n: int = 1
    """Keep every n-th frame of the video (or image of the sorted folder); 10 suits 30 fps footage."""
    matcher: Literal["auto", "exhaustive", "sequential"] = "auto"
    """exhaustive: every pair (unordered photos); sequential: 10 successors by name (video); auto: by input."""
    max_size: int = 1600
    """Longest image side in pixels; larger images are downscaled (Lanczos) before SfM. 0 keeps the size."""
    camera_model: str = "OPENCV"
    """COLMAP camera model, one camera for all images: OPENCV (flat-port distortion), RADIAL, SIMPLE_RADIAL, ..."""
    camera_params: str | None = None
    """Known intrinsics, kept fixed: COLMAP's order at the processed size, e.g. OPENCV fx,fy,cx,cy,k1,k2,p1,p2."""
    min_registered: float = 0.5
    """Fail, with advice, when structure from motion poses fewer than this share of the images."""
    verbose: bool = False
    """Show COLMAP's own log lines."""
    threads: int = -1
    """CPU threads for feature extraction, matching and mapping; -1 uses every core."""
    train_minutes: float = 30.0
    """The suggested `uw-train` command at the end is sized to train in about this long on this machine's CPU
    (downscale factor, then steps; uw3dgs/engine/run_size.py). On a GPU: 3DGS's own size and steps."""
    train_steps: int = 6000
    """Steps of the suggested command on a CPU (fewer only when even a coarse downscale would not fit)."""
    step_cost: StepCost = StepCost()
    """The CPU cost model of the suggestion (docs/run-time.md)."""


class ProcessDataError(ValueError):
    """The input cannot be processed as asked; the message says why and what to do."""


def check_out(out: Path) -> None:
    if out.exists() and (not out.is_dir() or any(out.iterdir())):
        raise ProcessDataError(f"--out {out} exists and is not an empty folder; choose a new folder (nothing is "
                               "overwritten)")


def extract_video_frames(video: Path, every_n: int, frames_dir: Path) -> list[str]:
    """Every n-th frame of `video` (frames 0, n, 2n, ...) as PNGs frame_00001.png, ... in frames_dir, decoded by
    imageio-ffmpeg's ffmpeg program; returns their names."""
    try:
        ffmpeg = ffmpeg_executable()
    except RuntimeError as err:
        raise ProcessDataError(
            f"--video: {err}; or extract the frames with any ffmpeg yourself: ffmpeg -i {video} -vf "
            f"\"select=not(mod(n\\,{every_n}))\" -fps_mode vfr frames/%05d.png  and pass --images frames"
        ) from err
    if not video.is_file():
        raise ProcessDataError(f"--video {video}: no such file")
    frames_dir.mkdir(parents=True, exist_ok=True)
    # -fps_mode (ffmpeg 5.1 and later), not -vsync: the bundled ffmpeg (9.x) no longer accepts -vsync
    cmd = [ffmpeg, "-hide_banner", "-loglevel", "error", "-nostdin", "-i", str(video),
           "-vf", f"select=not(mod(n\\,{every_n}))", "-fps_mode", "vfr", str(frames_dir / "frame_%05d.png")]
    result = subprocess.run(cmd, capture_output=True, text=True)
    if result.returncode != 0:
        raise ProcessDataError(f"ffmpeg could not read {video}: {result.stderr.strip() or result.returncode}")
    names = list_images(frames_dir)
    if not names:
        raise ProcessDataError(f"ffmpeg wrote no frame from {video}; is it a video file?")
    return names


def select_images(folder: Path, every_n: int) -> list[str]:
    if not folder.is_dir():
        raise ProcessDataError(f"--images {folder}: no such folder")
    names = list_images(folder)
    if not names:
        raise ProcessDataError(f"--images {folder}: no image (PNG, JPEG, TIFF, BMP) found")
    return names[::every_n]


def resize_images(src: Path, names: list[str], dst: Path, max_size: int, bar: Progress) -> bool:
    """Copies of the images whose longest side is above max_size, downscaled into dst (the others linked or
    copied), keeping format and EXIF (COLMAP reads the focal length prior from it). False when none is larger."""
    sizes = [image_size(src / n) for n in names]
    if max_size <= 0 or max(max(s) for s in sizes) <= max_size:
        return False
    task = bar.add_task("resizing", total=len(names))
    for name, (w, h) in zip(names, sizes, strict=True):
        target = dst / name
        target.parent.mkdir(parents=True, exist_ok=True)
        scale = max_size / max(w, h)
        if scale >= 1:
            shutil.copy2(src / name, target)
        else:
            with Image.open(src / name) as image:
                exif = image.info.get("exif")
                small = image.resize((max(1, round(w * scale)), max(1, round(h * scale))), Image.Resampling.LANCZOS)
                if target.suffix.lower() in (".jpg", ".jpeg"):
                    small.save(target, quality=95, **({"exif": exif} if exif else {}))
                else:
                    small.save(target)
        bar.advance(task)
    return True


def parse_camera(model: str, params: str | None, width: int, height: int) -> FixedCamera | None:
    if params is None:
        return None
    try:
        values = tuple(float(v) for v in params.replace(" ", "").split(",") if v)
    except ValueError as err:
        raise ProcessDataError(f"--camera-params {params!r}: not a comma-separated list of numbers") from err
    try:
        return FixedCamera(model, width, height, values)
    except ValueError as err:
        raise ProcessDataError(f"--camera-params: {err}") from err


def undistort(sparse_dir: Path, image_dir: Path, out: Path) -> None:
    """COLMAP's undistorter: out/images/ and out/sparse/0/ with PINHOLE cameras (nothing else kept). `out` is
    the dataset's staging folder (see `process`): it appears as a whole or not at all."""
    with tempfile.TemporaryDirectory(prefix=".undistort-", dir=out) as scratch:
        with quiet_colmap():
            pycolmap.undistort_images(scratch, str(sparse_dir), str(image_dir))
        (Path(scratch) / "images").rename(out / "images")
        (out / "sparse").mkdir(exist_ok=True)
        (Path(scratch) / "sparse").rename(out / "sparse" / "0")


def plausibility_warning(camera: pycolmap.Camera) -> str | None:
    """A self-calibrated field of view outside what underwater cameras have hints at a degenerate solution."""
    fov = float(np.degrees(2 * np.arctan(0.5 * camera.width / camera.focal_length_x)))
    if 20.0 <= fov <= 150.0:
        return None
    return (f"the estimated horizontal field of view is {fov:.0f} degrees, unusual for an underwater camera: "
            "self-calibration may have failed (a near-flat seabed leaves the focal length poorly determined). "
            "Pass the camera's intrinsics with --camera-params, or add images with more relief or more angles")


def process(args: ProcessDataArgs, console: Console, progress: bool = True) -> dict:
    """Run the whole pipeline; returns a summary (counts, sizes, timings)."""
    if (args.images is None) == (args.video is None):
        raise ProcessDataError("give exactly one of --images DIR and --video FILE")
    if args.every_n < 1:
        raise ProcessDataError(f"--every-n must be at least 1, got {args.every_n}")
    if args.threads == 0 or args.threads < -1:
        raise ProcessDataError(f"--threads must be -1 (every core) or at least 1, got {args.threads}")
    if args.train_minutes <= 0 or args.train_steps < 1:
        raise ProcessDataError(f"--train-minutes ({args.train_minutes}) must be positive and --train-steps "
                               f"({args.train_steps}) at least 1")
    check_out(args.out)
    start = time.perf_counter()
    args.out.mkdir(parents=True, exist_ok=True)
    # Everything is written to a hidden sibling of --out, which replaces the (empty) --out once complete: a
    # failed or killed run leaves --out empty, so the same command with other options can simply be re-run.
    target = args.out.resolve() if args.out.is_symlink() else args.out  # a link to a folder: fill the folder
    with atomic_folder(target, replace=True) as staged:
        summary = _process(args, staged, console, progress, start)
        check_out(args.out)  # still empty: never replace what appeared there meanwhile
    return summary


def _process(args: ProcessDataArgs, out: Path, console: Console, progress: bool, start: float) -> dict:
    """The pipeline, writing the dataset into `out` (the staging folder of --out)."""
    work = out / "colmap"
    work.mkdir()
    matcher = args.matcher if args.matcher != "auto" else ("sequential" if args.video else "exhaustive")
    scratch = Path(tempfile.mkdtemp(prefix=".input-", dir=out))
    try:
        if args.video is not None:
            console.print(f"extracting every {args.every_n}th frame of {args.video} with ffmpeg ...")
            source, names = scratch / "frames", extract_video_frames(args.video, args.every_n, scratch / "frames")
        else:
            source, names = args.images, select_images(args.images, args.every_n)
        with Progress(console=console, disable=not progress, transient=True) as bar:
            if resize_images(source, names, scratch / "resized", args.max_size, bar):
                source = scratch / "resized"
        width, height = image_size(source / names[0])
        camera = parse_camera(args.camera_model, args.camera_params, width, height)
        sparse = run_sfm(source, work, camera, matcher, progress=progress, image_names=names,
                         camera_model=args.camera_model, min_registered_fraction=args.min_registered,
                         verbose=args.verbose, num_threads=args.threads)
        rec = pycolmap.Reconstruction(str(sparse))
        console.print("undistorting to pinhole cameras ...")
        undistort(sparse, source, out)
    finally:
        shutil.rmtree(scratch, ignore_errors=True)
    cam = next(iter(rec.cameras.values()))
    return {"images": len(names), "registered": rec.num_reg_images(), "points": rec.num_points3D(),
            "matcher": matcher, "camera": cam, "fixed": camera is not None, "seconds": time.perf_counter() - start,
            "warning": None if camera is not None else plausibility_warning(cam)}


def summary_table(args: ProcessDataArgs, info: dict) -> Table:
    cam: pycolmap.Camera = info["camera"]
    table = Table(title=f"COLMAP dataset written in {info['seconds']:.1f} s", show_header=False)
    params = ", ".join(f"{p:.4g}" for p in cam.params)
    rows = [
        ("images", f"{info['registered']} of {info['images']} registered ({info['matcher']} matching)"),
        ("camera", f"{cam.model_name} {cam.width}x{cam.height} ({'fixed' if info['fixed'] else 'estimated'}): "
                   f"{params}"),
        ("points", f"{info['points']} in sparse/0/points3D.bin"),
        ("where", f"{args.out}/images, {args.out}/sparse/0 (undistorted, PINHOLE)"),
    ]
    for key, value in rows:
        table.add_row(key, value)
    return table


def entrypoint(argv: Sequence[str] | None = None) -> None:
    args = tyro.cli(ProcessDataArgs, args=argv, prog="uw-process-data")
    console = Console()
    try:
        info = process(args, console)
    except (ProcessDataError, SfmError, ValueError, FileNotFoundError) as exc:
        exit_with_error(exc, console)
    console.print(summary_table(args, info))
    if info["warning"]:
        warn(info["warning"])
    device = "cuda" if torch.cuda.is_available() else "cpu"
    cam = info["camera"]
    size = size_run(cam.width, cam.height, device, 60.0 * args.train_minutes, args.train_steps, args.step_cost)
    console.print(suggestion("uw3dgs", str(args.out), size, device))


if __name__ == "__main__":
    entrypoint()
