"""`uw-render RUN/config.yml --path interpolate --outputs uwi,uri,depth --output video.mp4`: a trained run rendered
along a camera path, the chosen outputs side by side and labelled, as an H.264 .mp4 and/or one PNG per frame.

    uw-render RUN/config.yml                                       # RUN/render/interpolate.mp4
    uw-render RUN/config.yml --path spiral --output reef.mp4
    uw-render RUN/config.yml --path train --outputs uri --images out/     # the water-free image of every view

See docs/render.md.
"""

from __future__ import annotations

import contextlib
import math
import shutil
import sys
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Annotated, Any, Literal

import numpy as np
import torch
import tyro
from PIL import Image
from rich.console import Console
from rich.progress import track
from torch import Tensor

from uw3dgs.cameras import Camera
from uw3dgs.cli.errors import report_user_errors
from uw3dgs.utils.console import CONSOLE, info, route_warnings
from uw3dgs.utils.io import atomic_file, unwritable_reason

PATHS = ("test", "train", "interpolate", "spiral")


@dataclass(frozen=True)
class Output:
    """One image uw-render can show: its label in the frame, the key of `Model.get_outputs` it is made from."""

    label: str
    key: str
    description: str


OUTPUTS: dict[str, Output] = {
    "uwi": Output("UWI", "rgb", "the rendered underwater image, the one the method is trained to match (every "
                                "method; for 3dgs its only image)"),
    "uri": Output("URI", "uri", "the water-free image (methods that model the water: uw3dgs and its ablations, "
                                "seasplat)"),
    "depth": Output("range", "range", "the distance along each pixel's ray, turbo colours from near (red) to far "
                                      "(blue) on one scale for all frames; empty pixels black"),
    "attenuation": Output("attenuation", "attenuation", "the direct signal's transmission exp(-beta_D z) (methods "
                                                        "with a medium)"),
    "backscatter": Output("backscatter", "backscatter", "the water's own light B_inf (1 - exp(-beta_B z)) (methods "
                                                        "with a medium)"),
}
DEFAULT_OUTPUTS = ("uwi", "uri", "depth")

MIN_FPS, MAX_FPS = 0.01, 1000.0
"""The frame rates an .mp4 of uw-render may have (ffmpeg's time base cannot hold a rate near 0)."""

DEPTH_RANGE_SAMPLES = 5
"""Frames, spread evenly along the path, whose rendered ranges fix the depth colour scale of the whole render."""


@dataclass(frozen=True)
class RenderArgs:
    """Render a trained run along a camera path: its outputs side by side, to an .mp4 and/or PNG frames."""

    load_config: tyro.conf.Positional[Annotated[Path, tyro.conf.arg(metavar="CONFIG")]]
    """The run's config.yml (outputs/<scene>/<method>/<timestamp>/config.yml)."""
    path: Annotated[str, tyro.conf.arg(metavar="{test,train,interpolate,spiral}")] = "interpolate"
    """The cameras: test/train, the dataset's views in name order (their own intrinsics); interpolate, a smooth
    path through the training views in order; spiral, two turns around the mean training pose looking at the
    scene (interpolate and spiral take the first training view's intrinsics). See docs/render.md."""
    outputs: str | None = None
    """What each frame shows, side by side, comma-separated: uwi, uri, depth, attenuation, backscatter (those the
    method renders); default uwi,uri,depth as far as the method has them."""
    output: Path | None = None
    """The video, an .mp4 file (H.264, yuv420p); default RUN/render/<path>.mp4 unless --images is given."""
    images: Path | None = None
    """Also (or, without --output, only) write every frame as a PNG into this folder: named after the dataset's
    images for --path test/train (e.g. IMG_0042.png), frame_00000.png ... otherwise."""
    frames_per_view: int = 10
    """--path interpolate: frames from one training view to the next (the path has (views - 1) x this + 1)."""
    num_frames: int = 120
    """--path spiral: frames of the whole spiral."""
    fps: float = 24.0
    """Frames per second of the video, from 0.01 (a slide show) to 1000."""
    crf: int = 18
    """x264's constant rate factor: 0 lossless, 18 visually lossless, 23 ffmpeg's default, 51 worst."""
    downscale: int = 1
    """Render at 1/downscale of the cameras' size (intrinsics scaled as --downscale-factor does in training)."""
    labels: Literal["auto", "always", "never"] = "auto"
    """Label each output above it; auto: when more than one output is shown (a single one is the bare image)."""
    step: int | None = None
    """Render the checkpoint of this step (one the run kept) instead of the latest."""
    device: str = "auto"
    """Where to render: auto (CUDA when PyTorch sees a GPU, else the CPU), cpu, cuda."""
    max_hours: float = 24.0
    """Refuse a render estimated (before it starts: the frames times the first frame's render time) to take longer
    than this; raise it for a long render."""


def parse_outputs(text: str | None) -> list[str] | None:
    """The names of --outputs, in order; None for the default. ValueError naming the valid names for an unknown,
    repeated or missing one."""
    if text is None:
        return None
    names = [name.strip() for name in text.split(",") if name.strip()]
    unknown = [name for name in names if name not in OUTPUTS]
    if unknown or not names or len(set(names)) < len(names):
        problem = f"unknown output {', '.join(unknown)}" if unknown else "repeated or no output"
        raise ValueError(f"--outputs {text}: {problem}; give names separated by commas from "
                         f"{', '.join(OUTPUTS)}")
    return names


def check_args(args: RenderArgs) -> tuple[Path | None, Path | None]:
    """Everything about the arguments that is wrong before anything is loaded, as a ValueError naming the option;
    returns where the video and the PNG frames go (None: not written)."""
    if args.path not in PATHS:
        raise ValueError(f"--path {args.path}: unknown camera path; choose one of {', '.join(PATHS)}")
    for option, value in (("--frames-per-view", args.frames_per_view), ("--num-frames", args.num_frames),
                          ("--downscale", args.downscale)):
        if value < 1:
            raise ValueError(f"{option} must be at least 1, got {value}")
    if not 0 <= args.crf <= 51:
        raise ValueError(f"--crf must be between 0 and 51, got {args.crf}")
    if not (math.isfinite(args.fps) and MIN_FPS <= args.fps <= MAX_FPS):
        raise ValueError(f"--fps must be between {MIN_FPS:g} and {MAX_FPS:g} frames per second, got {args.fps}")
    if not (math.isfinite(args.max_hours) and args.max_hours > 0):
        raise ValueError(f"--max-hours must be a positive number of hours, got {args.max_hours}")
    parse_outputs(args.outputs)
    output = args.output
    if output is None and args.images is None:
        output = Path(args.load_config).parent / "render" / f"{args.path}.mp4"
    if output is not None and output.suffix.lower() != ".mp4":
        raise ValueError(f"--output {output}: uw-render writes H.264 .mp4 videos only; give a file name ending in "
                         ".mp4, or --images DIR for PNG frames")
    for option, path, folder in (("--output", output, False), ("--images", args.images, True)):
        problem = None if path is None else unwritable_reason(path, folder=folder)
        if problem is not None:
            raise ValueError(f"{option} {path}: {problem}")
    return output, args.images


def frame_count(path: str, datamanager: Any, frames_per_view: int, num_frames: int) -> int:
    """How many frames `path_cameras` makes, known before they are made."""
    if path in ("test", "train"):
        return len(datamanager.test_indices if path == "test" else datamanager.train_indices)
    if path == "interpolate":
        return (len(datamanager.train_indices) - 1) * frames_per_view + 1
    return num_frames


def check_cost(frames: int, seconds_per_frame: float, frame_bytes: int, images_dir: Path | None,
               max_hours: float) -> str:
    """What the render will cost, said before it starts ('N frames: about T, PNGs up to B'); ValueError naming the
    options when it would take more than `max_hours` or its PNG frames (at most `frame_bytes` each, uncompressed)
    would not fit on the disk of `images_dir`."""
    hours = frames * seconds_per_frame / 3600
    cost = f"{frames:,} frame(s): about {_duration(hours * 3600)} ({seconds_per_frame:.3f} s per frame)"
    if hours > max_hours:
        raise ValueError(f"{cost}, more than --max-hours {max_hours:g}; render fewer frames (--num-frames, "
                         "--frames-per-view) or a smaller image (--downscale), or raise --max-hours")
    if images_dir is not None:
        need = frames * frame_bytes
        folder = images_dir
        while not folder.exists() and folder != folder.parent:
            folder = folder.parent
        free = shutil.disk_usage(folder).free
        if need > free:
            raise ValueError(f"{cost}: their PNGs may need up to {need / 2**30:.1f} GiB and {folder} has "
                             f"{free / 2**30:.1f} GiB free; render fewer frames or a smaller image (--downscale), or "
                             "free some space")
        cost += f", PNGs up to {need / 2**20:,.0f} MiB"
    return cost


def _duration(seconds: float) -> str:
    if seconds < 120:
        return f"{seconds:.0f} s"
    if seconds < 7200:
        return f"{seconds / 60:.0f} min"
    return f"{seconds / 3600:,.1f} h"


def path_views(path: str, datamanager: Any) -> list[int]:
    """The dataset views a path starts from: the test views for `test`, else the training views."""
    indices = datamanager.test_indices if path == "test" else datamanager.train_indices
    if not indices:
        raise ValueError("--path test: the run has no test views (trained with --datamanager.llffhold 0); use "
                         "--path train")
    return indices


def path_cameras(path: str, datamanager: Any, frames_per_view: int, num_frames: int) -> tuple[list[Camera], list[str]]:
    """The cameras of `path` (see RenderArgs.path) and each frame's PNG file name, relative to --images: the dataset
    image's name with the suffix .png for test/train (subfolders kept), frame_<00000>.png for the others."""
    from uw3dgs.render.camera_path import camera_to_world, cameras_from_poses, interpolate_poses, spiral_poses

    scene = datamanager.scene
    if path in ("test", "train"):
        indices = path_views(path, datamanager)
        files = [str(Path(scene.image_names[i]).with_suffix(".png")) for i in indices]
        if len(set(files)) < len(files):
            raise ValueError(f"--path {path}: two images of the dataset differ only in their suffix, so their PNGs "
                             "would have one name; render a video instead (--output)")
        return [scene.cameras[i] for i in indices], files
    train = [scene.cameras[i] for i in datamanager.train_indices]
    keys = torch.stack([camera_to_world(camera) for camera in train])
    if path == "interpolate":
        poses = interpolate_poses(keys, frames_per_view)
    else:
        poses = spiral_poses(keys, scene.points, num_frames)
    cameras = cameras_from_poses(poses, train[0], path)
    return cameras, [f"frame_{k:05d}.png" for k in range(len(cameras))]


def depth_colors(ranges: Tensor, alpha: Tensor, scale: tuple[float, float]) -> Tensor:
    """Turbo colours [H, W, 3] of `ranges` [H, W] on the fixed scale (near, far), near red and far blue, as
    `depth_to_image` draws them, but on one scale for every frame so that a colour means one distance all along
    the video. Pixels below MIN_DEPTH_ALPHA coverage, non-finite or non-positive are black."""
    from uw3dgs.utils.visualize import MIN_DEPTH_ALPHA, apply_colormap

    valid = torch.isfinite(ranges) & (ranges > 0) & (alpha >= MIN_DEPTH_ALPHA)
    return apply_colormap(-ranges, vmin=-scale[1], vmax=-scale[0], mask=valid)


def depth_scale(model: Any, cameras: list[Camera], device: torch.device) -> tuple[float, float]:
    """(near, far): the ROBUST_PERCENTILES of the covered pixels' ranges over DEPTH_RANGE_SAMPLES frames spread
    along `cameras`; (0, 1) when none of them covers a pixel."""
    from uw3dgs.utils.visualize import MIN_DEPTH_ALPHA, ROBUST_PERCENTILES

    picks = sorted({round(k * (len(cameras) - 1) / max(DEPTH_RANGE_SAMPLES - 1, 1))
                    for k in range(DEPTH_RANGE_SAMPLES)})
    values = []
    for k in picks:
        out = model.get_outputs(cameras[k].to(device))
        ranges, valid = out["range"], out["alpha"] >= MIN_DEPTH_ALPHA
        values.append(ranges[valid & torch.isfinite(ranges) & (ranges > 0)].double().cpu().numpy())
    pooled = np.concatenate(values)
    if pooled.size == 0:
        return 0.0, 1.0
    near, far = np.percentile(pooled, ROBUST_PERCENTILES)
    return float(near), float(far)


def output_images(outputs: dict[str, Any], names: list[str], scale: tuple[float, float] | None) -> list[Tensor]:
    """The images [H, W, 3] in [0, 1] of `names` from one view's `Model.get_outputs`; `scale` is the depth colour
    scale (needed when 'depth' is among the names)."""
    images = []
    for name in names:
        value = outputs[OUTPUTS[name].key]
        images.append(depth_colors(value, outputs["alpha"], scale) if name == "depth" else value.clamp(0, 1))
    return images


def write_png(path: Path, frame: np.ndarray) -> None:
    """A uint8 frame [H, W, 3] as a PNG, atomically (an interrupted render leaves no truncated file)."""
    with atomic_file(path, "wb") as f:
        Image.fromarray(frame).save(f, format="PNG")


@torch.no_grad()
def run_render(args: RenderArgs, progress: bool = True) -> dict[str, Any]:
    """Render the run along the path; returns a summary: frames, (width, height) of a frame (before the video's
    padding to even sides), the outputs shown, the video and image folder written (None where not), seconds."""
    from uw3dgs.data.downscale import downscale_camera
    from uw3dgs.engine.evaluator import load_trained
    from uw3dgs.engine.signals import sigterm_as_interrupt
    from uw3dgs.engine.trainer import resolve_device
    from uw3dgs.utils.video import Mp4Writer, labelled_row

    output, images_dir = check_args(args)
    requested = parse_outputs(args.outputs)
    device = resolve_device(args.device)
    config, datamanager, model, _ = load_trained(args.load_config, device, step=args.step)
    model.eval()
    views = path_views(args.path, datamanager)
    smallest = min(min(datamanager.scene.cameras[i].width, datamanager.scene.cameras[i].height) for i in views)
    if args.downscale > smallest:
        raise ValueError(f"--downscale {args.downscale} leaves no pixel of a {smallest}-pixel side; choose at most "
                         f"{smallest}")
    # the first frame's camera (the paths but test take the first training view's intrinsics), rendered to see what
    # the method renders and, a second time, how long a frame takes, before the path's cameras are made
    probe_camera = downscale_camera(datamanager.scene.cameras[views[0]], args.downscale).to(device)
    probe = model.get_outputs(probe_camera)  # the first render may include one-off work (building the rasterizer)
    started = time.perf_counter()
    model.get_outputs(probe_camera)
    seconds = time.perf_counter() - started
    available = [name for name, spec in OUTPUTS.items() if spec.key in probe]
    names = requested or [name for name in DEFAULT_OUTPUTS if name in available]
    missing = [name for name in names if name not in available]
    if missing:
        raise ValueError(f"--outputs: a {config.method_name} run renders no {', '.join(missing)}; it can render "
                         f"{', '.join(available)}")
    labels = [OUTPUTS[name].label for name in names] if args.labels == "always" or (
        args.labels == "auto" and len(names) > 1) else None
    blank = labelled_row([torch.zeros(probe_camera.height, probe_camera.width, 3)] * len(names), labels)
    # a PNG is at most its pixels, a filter byte per row and zlib's stored-block overhead (5 bytes per 16 KiB) more
    frame_bytes = blank.nbytes + blank.shape[0] + blank.nbytes // 3000 + 1024
    info(check_cost(frame_count(args.path, datamanager, args.frames_per_view, args.num_frames), seconds,
                    frame_bytes, images_dir, args.max_hours))
    cameras, files = path_cameras(args.path, datamanager, args.frames_per_view, args.num_frames)
    cameras = [downscale_camera(camera, args.downscale) for camera in cameras]
    scale = depth_scale(model, cameras, device) if "depth" in names else None
    start = time.perf_counter()
    size = None
    with contextlib.ExitStack() as stack:
        stack.enter_context(sigterm_as_interrupt())  # after loading (pycolmap installs its own SIGTERM handler)
        video = None if output is None else stack.enter_context(Mp4Writer(output, args.fps, args.crf))
        for camera, file in track(list(zip(cameras, files, strict=True)), description="render", console=CONSOLE,
                                  disable=not progress):
            frame = labelled_row(output_images(model.get_outputs(camera.to(device)), names, scale), labels)
            size = (frame.shape[1], frame.shape[0])
            if video is not None:
                video.write(frame)
            if images_dir is not None:
                write_png(images_dir / file, frame)
    return {"frames": len(cameras), "size": size, "outputs": names, "output": output, "images": images_dir,
            "seconds": time.perf_counter() - start}


def entrypoint(argv: list[str] | None = None) -> None:
    argv = sys.argv[1:] if argv is None else argv
    route_warnings()
    args = tyro.cli(RenderArgs, args=argv, prog="uw-render", description=__doc__)
    try:
        result = report_user_errors(lambda: run_render(args))  # OSError: e.g. the disk filling up
    except KeyboardInterrupt as exc:  # Ctrl-C or SIGTERM: the unfinished video's temporary file is removed
        Console().print("Interrupted: no video written." if args.output or args.images is None else "Interrupted.")
        sys.exit(getattr(exc, "exit_code", 130))
    n, seconds = result["frames"], result["seconds"]
    info(f"rendered {n} frame(s) of {result['size'][0]}x{result['size'][1]} ({', '.join(result['outputs'])}) in "
         f"{seconds:.1f} s ({seconds / n:.3f} s per frame)")
    if result["output"] is not None:
        info(f"video written to {result['output']}")
    if result["images"] is not None:
        info(f"frames written to {result['images']}/")


if __name__ == "__main__":
    entrypoint()
