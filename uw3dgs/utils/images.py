"""Reading and writing image files as float RGB in [0, 1], with errors that say which file and why."""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np
import torch
from PIL import Image
from torch import Tensor

from uw3dgs.utils.io import atomic_file
from uw3dgs.utils.visualize import ArrayLike, to_uint8

# Pillow modes of 16-bit grayscale PNGs ("I" in older Pillow releases, "I;16*" in newer ones).
_SIXTEEN_BIT_GRAY_MODES = frozenset({"I", "I;16", "I;16B", "I;16L", "I;16N"})


class ImageReadError(ValueError):
    """An image file could not be read or decoded; the message names the file and a fix."""


def _fix_hint(error: Exception) -> str:
    """What the user can do about a failed read, by cause."""
    if isinstance(error, FileNotFoundError):
        return "check the path and that the image folder matches the dataset's image list"
    if isinstance(error, PermissionError):
        return "check the file's read permissions"
    return (
        "the file is truncated or corrupt (an interrupted copy or download?): copy or export it again, "
        "or remove it and its camera from the dataset"
    )


def _to_float_rgb(image: Image.Image) -> np.ndarray:
    """Decoded Pillow image -> float32 [H, W, 3] in [0, 1]; alpha is dropped, not composited."""
    if image.mode in _SIXTEEN_BIT_GRAY_MODES:
        gray = np.asarray(image, dtype=np.float32) / 65535.0
        return np.repeat(gray.clip(0.0, 1.0)[..., None], 3, axis=-1)
    # Pillow decodes 16-bit RGB(A) PNGs to 8 bits per channel, so those arrive here at 1/255 precision.
    return np.asarray(image.convert("RGB"), dtype=np.float32) / 255.0


def read_image(path: str | os.PathLike) -> Tensor:
    """Read a PNG/JPEG as a float32 tensor [H, W, 3] in [0, 1].

    Grayscale becomes three equal channels, alpha is dropped, 16-bit grayscale is scaled by 1/65535.
    EXIF orientation is ignored: camera intrinsics refer to the stored pixel grid. Raises
    ImageReadError for missing, unreadable, truncated or corrupt files.
    """
    path = Path(path)
    try:
        with Image.open(path) as image:
            image.load()  # open() only parses the header; decoding now is what detects truncation
            pixels = _to_float_rgb(image)
    except (OSError, SyntaxError) as error:  # Pillow reports corrupt PNG chunks as SyntaxError
        raise ImageReadError(f"cannot read image {path}: {error}; {_fix_hint(error)}") from error
    return torch.from_numpy(np.ascontiguousarray(pixels))


def image_size(path: str | os.PathLike) -> tuple[int, int]:
    """(width, height) from the file header, without decoding the pixels; ImageReadError if unreadable."""
    path = Path(path)
    try:
        with Image.open(path) as image:
            return image.size
    except (OSError, SyntaxError) as error:
        raise ImageReadError(f"cannot read image {path}: {error}; {_fix_hint(error)}") from error


def write_image(path: str | os.PathLike, img: ArrayLike) -> None:
    """Write a float [H, W, 3] image in [0, 1] (or a uint8 one, as `labelled_row` makes, as it is) as an 8-bit PNG,
    atomically.

    The PNG goes to a temporary file in the target folder and is renamed over `path`, so an
    interrupted run never leaves a truncated image that a later evaluation would trip over.
    """
    path = Path(path)
    if path.suffix.lower() != ".png":
        raise ValueError(f"write_image writes PNG files only, got {path}")
    pixels = to_uint8(img)
    if pixels.ndim != 3 or pixels.shape[-1] != 3:
        raise ValueError(f"write_image expects an [H, W, 3] image, got shape {pixels.shape}")
    with atomic_file(path, "wb", fsync=True) as f:
        Image.fromarray(pixels).save(f, format="PNG")
