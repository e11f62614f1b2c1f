"""Video frames and files: rendered images side by side with text labels, and H.264 .mp4 writing through the ffmpeg
program that the imageio-ffmpeg package ships (no system ffmpeg needed).

    with Mp4Writer(path, fps=24) as video:
        for images in renders:
            video.write(labelled_row(images, ["UWI", "URI"]))
"""

from __future__ import annotations

import contextlib
import os
import subprocess
import tempfile
import uuid
from fractions import Fraction
from pathlib import Path

import numpy as np
from PIL import Image, ImageDraw, ImageFont

from uw3dgs.utils.visualize import SEPARATOR_PX, ArrayLike, image_grid, to_uint8

LABEL_PADDING_PX = 3
"""Space around a label's text in its strip above the tile."""

MIN_FONT_PX = 10
"""The labels' font size on small tiles; larger tiles get 1/20 of their height."""


def ffmpeg_executable() -> str:
    """The ffmpeg program of the imageio-ffmpeg package (or the one its IMAGEIO_FFMPEG_EXE environment variable
    names). RuntimeError, saying how to get one, when the package or its binary is missing."""
    try:
        import imageio_ffmpeg
    except ImportError as err:
        raise RuntimeError("video needs the imageio-ffmpeg package (it ships an ffmpeg program): "
                           "pip install imageio-ffmpeg") from err
    try:
        return imageio_ffmpeg.get_ffmpeg_exe()
    except RuntimeError as err:  # a platform without a bundled binary and no ffmpeg on PATH
        raise RuntimeError(f"no ffmpeg program found ({err}); install ffmpeg, or point IMAGEIO_FFMPEG_EXE at "
                           "one") from err


def labelled_row(tiles: list[ArrayLike], labels: list[str] | None = None) -> np.ndarray:
    """Equally sized float images [H, W, 3] in [0, 1] side by side (white separators, as `image_grid` draws them)
    as one uint8 RGB frame; with `labels` (one per tile) a black strip above holds each tile's label in white,
    left-aligned over its tile and cut at the tile's width. Without labels the frame is exactly the tiles'
    `to_uint8` pixels (one tile: that image)."""
    row = to_uint8(image_grid(tiles))
    if labels is None:
        return row
    if len(labels) != len(tiles):
        raise ValueError(f"labelled_row: {len(tiles)} tiles but {len(labels)} labels")
    height, width = np.asarray(tiles[0]).shape[:2]
    font = ImageFont.load_default(size=max(MIN_FONT_PX, round(height / 20)))
    # getbbox, not the size: without FreeType Pillow falls back to a fixed bitmap font that has no size
    strip_height = font.getbbox("Ag")[3] + 2 * LABEL_PADDING_PX
    strip = Image.new("RGB", (row.shape[1], strip_height))
    for k, label in enumerate(labels):
        cell = Image.new("RGB", (width, strip_height))  # drawn apart, so a long label stops at its own tile
        ImageDraw.Draw(cell).text((LABEL_PADDING_PX, LABEL_PADDING_PX), label, fill=(255, 255, 255), font=font)
        strip.paste(cell, (k * (width + SEPARATOR_PX), 0))
    return np.concatenate([np.asarray(strip), row], axis=0)


def pad_to_even(frame: np.ndarray) -> np.ndarray:
    """`frame` [H, W, 3] with a black row and/or column added at the bottom/right where H or W is odd: H.264 in
    yuv420p stores colour per 2 x 2 pixels, so its frame sides must be even."""
    height, width = frame.shape[:2]
    return np.pad(frame, ((0, height % 2), (0, width % 2), (0, 0)))


class Mp4Writer:
    """Write uint8 RGB frames [H, W, 3] of one size to an H.264 .mp4 (yuv420p, plays in browsers and players),
    atomically: ffmpeg writes a temporary file beside `path` (`.<name>.<hex>.tmp`, as `uw3dgs.utils.io` names
    them) that replaces `path` when the context exits cleanly; on an exception it is removed and `path` is left as
    it was. Odd frame sides are padded to even (`pad_to_even`). `crf` is x264's constant rate factor: 0 lossless,
    18 visually lossless, 23 ffmpeg's default, 51 worst."""

    def __init__(self, path: str | os.PathLike, fps: float, crf: int = 18):
        self.path = Path(path)
        self.fps = fps
        self.crf = crf
        self.frames = 0
        self.size: tuple[int, int] | None = None
        """(width, height) of the video, after padding; set by the first frame."""
        self._tmp = self.path.with_name(f".{self.path.name}.{uuid.uuid4().hex}.tmp")
        self._process: subprocess.Popen | None = None
        self._files = contextlib.ExitStack()

    def __enter__(self) -> Mp4Writer:
        self.path.parent.mkdir(parents=True, exist_ok=True)
        # ffmpeg's messages go to a file, not a pipe: a full pipe nobody reads would stall it
        self._log = self._files.enter_context(tempfile.TemporaryFile())
        return self

    def _start(self, width: int, height: int) -> None:
        rate = Fraction(self.fps).limit_denominator(100_000)  # 30000/1001 stays exact
        cmd = [ffmpeg_executable(), "-y", "-hide_banner", "-loglevel", "error",
               "-f", "rawvideo", "-pix_fmt", "rgb24", "-s", f"{width}x{height}", "-r", str(rate), "-i", "-", "-an",
               "-c:v", "libx264", "-pix_fmt", "yuv420p", "-crf", str(self.crf),
               # the index at the front: a browser starts playing before the whole file is downloaded
               "-movflags", "+faststart", "-f", "mp4", str(self._tmp)]
        self._process = subprocess.Popen(cmd, stdin=subprocess.PIPE, stdout=subprocess.DEVNULL, stderr=self._log)
        self.size = (width, height)

    def write(self, frame: np.ndarray) -> None:
        """Append one uint8 frame [H, W, 3]; every frame must have the first one's size."""
        if frame.dtype != np.uint8 or frame.ndim != 3 or frame.shape[2] != 3:
            raise ValueError(f"Mp4Writer takes uint8 [H, W, 3] frames, got {frame.dtype} {frame.shape}")
        frame = pad_to_even(frame)
        height, width = frame.shape[:2]
        if self._process is None:
            self._start(width, height)
        elif (width, height) != self.size:
            raise ValueError(f"frame {self.frames} is {width}x{height}, the video {self.size[0]}x{self.size[1]}")
        try:
            self._process.stdin.write(np.ascontiguousarray(frame).tobytes())
        except BrokenPipeError:  # ffmpeg stopped: its log says why
            self._process.wait()
            raise RuntimeError(f"ffmpeg stopped writing {self.path}: {self._ffmpeg_message()}") from None
        self.frames += 1

    def _ffmpeg_message(self) -> str:
        self._log.seek(0)
        lines = self._log.read().decode(errors="replace").strip().splitlines()
        return lines[-1] if lines else f"exit status {self._process.returncode}"

    def __exit__(self, exc_type, exc, tb) -> None:
        try:
            if self._process is not None:
                # closing flushes the last frames, which fails if ffmpeg has stopped: its exit status says so below
                with contextlib.suppress(BrokenPipeError):
                    self._process.stdin.close()
                if exc_type is None:
                    self._process.wait()
                else:  # interrupted or failed: the partial file is thrown away anyway
                    self._process.kill()
                    self._process.wait()
            if exc_type is not None:
                return
            if self._process is None:
                raise ValueError(f"no frames to write to {self.path}")
            if self._process.returncode != 0:
                raise RuntimeError(f"ffmpeg could not write {self.path}: {self._ffmpeg_message()}")
            os.replace(self._tmp, self.path)
        finally:
            self._tmp.unlink(missing_ok=True)
            self._files.close()
