"""UWBundle's `.calib` stereo calibration: reading, writing, and the fixed SfM cameras it gives."""

from __future__ import annotations

import re
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from uw3dgs.data.sfm import FixedCamera


class CalibError(ValueError):
    """A malformed .calib file; the message names the file and the line."""


@dataclass(eq=False)
class CalibCamera:
    """One camera of the stereo calibration, in OpenCV's conventions (as calibration tools write them)."""

    width: int
    height: int
    K: np.ndarray
    """3x3 intrinsics, OpenCV pixel convention: the centre of the top-left pixel is (0, 0)."""
    dist: np.ndarray
    """(k1, k2, p1, p2, k3): OpenCV's 5-parameter ("plumb bob") distortion."""
    R: np.ndarray
    """3x3 rotation and ..."""
    t: np.ndarray
    """... translation from the reference frame into this camera: x_cam = R x_ref + t. The reference is
    normally the left camera (identity, zero for it)."""

    def fixed_camera(self) -> FixedCamera:
        """The COLMAP camera: OPENCV when k3 = 0, else FULL_OPENCV with k4 = k5 = k6 = 0, which is exactly
        OpenCV's 5-parameter model (dropping k3 would bend the image edges: r^6 matters in the corners).
        COLMAP puts the centre of the top-left pixel at (0.5, 0.5): cx and cy gain 0.5."""
        fx, fy = float(self.K[0, 0]), float(self.K[1, 1])
        cx, cy = float(self.K[0, 2]) + 0.5, float(self.K[1, 2]) + 0.5
        k1, k2, p1, p2, k3 = (float(x) for x in self.dist)
        if k3 == 0.0:
            return FixedCamera("OPENCV", self.width, self.height, (fx, fy, cx, cy, k1, k2, p1, p2))
        return FixedCamera("FULL_OPENCV", self.width, self.height,
                           (fx, fy, cx, cy, k1, k2, p1, p2, k3, 0.0, 0.0, 0.0))


@dataclass(eq=False)
class StereoCalibration:
    left: CalibCamera
    right: CalibCamera
    rectification: np.ndarray = field(default_factory=lambda: np.zeros(0))
    """Whatever numbers follow the two cameras (rectification rotations / projections), kept as read; unused."""
    path: Path | None = None

    def right_from_left(self) -> tuple[np.ndarray, np.ndarray]:
        """(R, t) with x_right = R x_left + t."""
        R = self.right.R @ self.left.R.T
        return R, self.right.t - R @ self.left.t

    @property
    def baseline(self) -> float:
        """Distance between the two camera centres, in the calibration's units."""
        return float(np.linalg.norm(self.right_from_left()[1]))


_NUMBERS_PER_CAMERA = (("image size (width height)", 2), ("camera matrix K (3x3)", 9),
                       ("distortion (k1 k2 p1 p2 k3)", 5), ("rotation R (3x3)", 9), ("translation t (3)", 3))
_LABEL = re.compile(r"^[A-Za-z_][\w\-]*\s*[:=]$")
_WORD = re.compile(r"^[A-Za-z_][\w\-]*[:=]?$")


def _tokens(path: Path, text: str) -> Iterator[tuple[float, int]]:
    """(number, line) for every number; '#' and '%' start comments; a line of plain words is a label; a
    leading 'name:' label on a line of numbers is dropped. Anything else that is not a number is an error."""
    for lineno, raw in enumerate(text.splitlines(), start=1):
        line = re.split(r"[#%]", raw, maxsplit=1)[0].replace(",", " ").replace(";", " ")
        words = line.replace("[", " ").replace("]", " ").split()
        if words and _LABEL.match(words[0]):
            words = words[1:]
        values = []
        for word in words:
            try:
                values.append(float(word))
            except ValueError:
                values.append(None)
        if all(v is None and _WORD.match(w) for w, v in zip(words, values, strict=True)):
            continue  # blank, comment or label line ("left camera", "K1:", "[right]")
        bad = [w for w, v in zip(words, values, strict=True) if v is None or not np.isfinite(v)]
        if bad:
            raise CalibError(f"{path}:{lineno}: {bad[0]!r} is not a number (line: {raw.strip()!r}); "
                             "see docs/uwbundle.md for the .calib format")
        for value in values:
            yield value, lineno


def _camera(path: Path, numbers: list[tuple[float, int]], start: int, which: str) -> CalibCamera:
    parts: dict[str, tuple[np.ndarray, int]] = {}
    pos = start
    for name, count in _NUMBERS_PER_CAMERA:
        chunk = numbers[pos : pos + count]
        if len(chunk) < count:
            last = numbers[-1][1] if numbers else 0
            raise CalibError(f"{path}:{last}: the file ends after {len(numbers)} numbers, in the {which} camera's "
                             f"{name} (each camera needs 28 numbers: width height, K, k1 k2 p1 p2 k3, R, t); "
                             "see docs/uwbundle.md for the .calib format")
        parts[name] = (np.array([v for v, _ in chunk]), chunk[0][1])
        pos += count
    (size, size_line), (K, k_line) = parts["image size (width height)"], parts["camera matrix K (3x3)"]
    if any(s <= 0 or s != int(s) for s in size):
        raise CalibError(f"{path}:{size_line}: the {which} camera's image size must be two positive integers "
                         f"(width height), got {size[0]:g} {size[1]:g}")
    K = K.reshape(3, 3)
    if not (K[0, 0] > 0 and K[1, 1] > 0 and np.allclose(K[1, 0], 0) and np.allclose(K[2], [0, 0, 1])):
        raise CalibError(f"{path}:{k_line}: the {which} camera's K is not a camera matrix "
                         f"[[fx s cx] [0 fy cy] [0 0 1]] with fx, fy > 0: got {K.tolist()}")
    R, r_line = parts["rotation R (3x3)"]
    R = R.reshape(3, 3)
    if not (np.allclose(R @ R.T, np.eye(3), atol=1e-4) and np.linalg.det(R) > 0):
        raise CalibError(f"{path}:{r_line}: the {which} camera's R is not a rotation matrix "
                         f"(|R R^T - I| = {np.abs(R @ R.T - np.eye(3)).max():.2g}, det = {np.linalg.det(R):.4g})")
    return CalibCamera(int(size[0]), int(size[1]), K, parts["distortion (k1 k2 p1 p2 k3)"][0], R,
                       parts["translation t (3)"][0])


def read_calib(path: Path) -> StereoCalibration:
    """Parse a stereo .calib text file: for the left then the right camera, width height, K (3x3, row by row),
    k1 k2 p1 p2 k3, R (3x3), t (3); then optional rectification numbers. Numbers are read in order whatever
    the line breaks; raises CalibError naming the file and line of the first problem."""
    path = Path(path)
    try:
        text = path.read_text(errors="strict")
    except UnicodeDecodeError as err:
        raise CalibError(f"{path}: not a text file ({err}); a .calib file lists numbers as text") from err
    numbers = list(_tokens(path, text))
    left = _camera(path, numbers, 0, "left")
    right = _camera(path, numbers, 28, "right")
    rectification = np.array([v for v, _ in numbers[56:]])
    calib = StereoCalibration(left, right, rectification, path)
    if calib.baseline <= 0:
        raise CalibError(f"{path}: both cameras are at the same place (zero baseline); check the translations")
    return calib


def _rows(values: np.ndarray, width: int) -> str:
    """Rows of `width` numbers, each in Python's shortest form that reads back to the same float."""
    rows = np.asarray(values, dtype=float).reshape(-1, width)
    return "\n".join(" ".join(repr(float(v)) for v in row) for row in rows)


def write_calib(path: Path, calib: StereoCalibration) -> None:
    """Write `calib` in the format `read_calib` reads (with comments), exactly (17 significant digits)."""
    parts = ["# stereo calibration (uw3dgs .calib): per camera width height, K, k1 k2 p1 p2 k3, R, t "
             "(x_cam = R x_left + t)"]
    for name, cam in (("left", calib.left), ("right", calib.right)):
        parts += [f"# {name} camera", f"{cam.width} {cam.height}", _rows(cam.K, 3), _rows(cam.dist, 5),
                  _rows(cam.R, 3), _rows(cam.t, 3)]
    if calib.rectification.size:
        rect = calib.rectification
        parts += ["# rectification", _rows(rect, 9 if rect.size % 9 == 0 else rect.size)]
    Path(path).write_text("\n".join(parts) + "\n")
