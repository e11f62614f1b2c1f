"""Datamanager `uwbundle`: UWBundle (Skinner et al. 2017) stereo captures, posed by structure from motion.

Layout (see docs/uwbundle.md):

    ROOT/*.calib             the stereo calibration (exactly one .calib file)
    ROOT/left/  ROOT/right/  the two cameras' images (or ROOT/images/left/ and ROOT/images/right/);
                             a stereo pair shares its file name stem (left/0001.png <-> right/0001.jpg)
    ROOT/groundtruth.ply     optional: ground-truth surface (mesh or point cloud, ASCII or binary PLY)
    ROOT/sparse/0/           optional: a COLMAP model; written by the first load when absent

UWBundle ships no poses, so the first load runs structure from motion (`uw3dgs.data.sfm.run_sfm`) with the
calibration as fixed intrinsics, scales the model to the calibration's units with the stereo baseline, and
caches it (ROOT/sparse/0 when ROOT is writable, else under $UW3DGS_CACHE or ~/.cache/uw3dgs). Later loads
read the cached model through `read_colmap_dataset` (undistortion, downscaling, image cache).
"""

from __future__ import annotations

import hashlib
import json
import os
import re
import shutil
import sys
import tempfile
import time
import uuid
from collections.abc import Iterator
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Literal

import numpy as np
import pycolmap
import torch
from torch import Tensor

from uw3dgs.config import Target, target
from uw3dgs.data import colmap_dataset
from uw3dgs.data.cache import default_cache_dir
from uw3dgs.data.datamanager import DataManager, DataManagerConfig
from uw3dgs.data.scene import SceneData
from uw3dgs.data.sfm import IMAGE_EXTENSIONS, FixedCamera, image_size, list_images, quiet_colmap, run_sfm
from uw3dgs.registry import DataManagerSpec

SFM_VERSION = 1
"""Bump when the SfM recipe changes: it is part of the cache key, so cached models are rebuilt."""
STAMP = "uw3dgs_sfm.json"
"""Written next to a model this datamanager made (ROOT/sparse/uw3dgs_sfm.json): its cache key and stats."""
SIDES = ("left", "right")


# ----------------------------------------------------------------------------------------------------
# The .calib file


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


# ----------------------------------------------------------------------------------------------------
# PLY vertices


_PLY_TYPES = {"char": "i1", "int8": "i1", "uchar": "u1", "uint8": "u1", "short": "i2", "int16": "i2",
              "ushort": "u2", "uint16": "u2", "int": "i4", "int32": "i4", "uint": "u4", "uint32": "u4",
              "float": "f4", "float32": "f4", "double": "f8", "float64": "f8"}


@dataclass
class _PlyElement:
    name: str
    count: int
    properties: list[tuple[str, str, str | None]] = field(default_factory=list)
    """(name, type, list-count type or None)."""


def _ply_header(path: Path, data: bytes) -> tuple[str, list[_PlyElement], int]:
    end = data.find(b"end_header")
    if not data.startswith(b"ply") or end < 0:
        raise ValueError(f"{path}: not a PLY file (no 'ply' magic or no 'end_header')")
    body = data.index(b"\n", end) + 1
    fmt, elements = "", []
    for lineno, line in enumerate(data[:end].decode("ascii", errors="replace").splitlines(), start=1):
        words = line.split()
        if not words or words[0] in ("ply", "comment", "obj_info"):
            continue
        if words[0] == "format":
            fmt = words[1]
        elif words[0] == "element":
            elements.append(_PlyElement(words[1], int(words[2])))
        elif words[0] == "property" and elements:
            if words[1] == "list":
                elements[-1].properties.append((words[4], words[3], words[2]))
            else:
                elements[-1].properties.append((words[2], words[1], None))
        else:
            raise ValueError(f"{path}:{lineno}: unexpected PLY header line {line.strip()!r}")
    for el in elements:
        for name, typ, count_type in el.properties:
            if typ not in _PLY_TYPES or (count_type is not None and count_type not in _PLY_TYPES):
                raise ValueError(f"{path}: property {name!r} of element {el.name!r} has unknown type {typ!r}")
    if fmt not in ("ascii", "binary_little_endian", "binary_big_endian"):
        raise ValueError(f"{path}: unknown PLY format {fmt!r}")
    return fmt, elements, body


def read_ply_points(path: Path) -> np.ndarray:
    """Vertex positions [N, 3] (float64) of a PLY mesh or point cloud, ASCII or binary; faces are ignored."""
    path = Path(path)
    data = path.read_bytes()
    fmt, elements, offset = _ply_header(path, data)
    vertex = next((el for el in elements if el.name == "vertex"), None)
    if vertex is None:
        raise ValueError(f"{path}: no 'vertex' element in the PLY header")
    names = [p[0] for p in vertex.properties]
    if not {"x", "y", "z"} <= set(names) or any(p[2] is not None for p in vertex.properties):
        raise ValueError(f"{path}: the vertex element needs scalar x, y, z properties, has {names}")
    cols = [names.index(a) for a in "xyz"]
    if fmt == "ascii":
        lines = data[offset:].decode("ascii", errors="replace").splitlines()
        skip = 0
        for el in elements:  # elements before the vertices take one line per item
            if el is vertex:
                break
            skip += el.count
        rows = [line for line in lines[skip:] if line.strip()][: vertex.count]
        if len(rows) < vertex.count:
            raise ValueError(f"{path}: {len(rows)} vertex lines for {vertex.count} vertices (truncated file?)")
        try:
            table = np.array([row.split()[: len(names)] for row in rows], dtype=np.float64)
        except ValueError as err:
            raise ValueError(f"{path}: malformed ASCII vertex line ({err})") from err
        return table[:, cols].reshape(-1, 3)
    endian = "<" if fmt == "binary_little_endian" else ">"
    for el in elements:
        if el is vertex:
            break
        offset = _skip_binary_element(path, data, offset, el, endian)
    dtype = np.dtype([(n, endian + _PLY_TYPES[t]) for n, t, _ in vertex.properties])
    if offset + dtype.itemsize * vertex.count > len(data):
        raise ValueError(f"{path}: file ends inside the vertex data (truncated download?)")
    table = np.frombuffer(data, dtype=dtype, count=vertex.count, offset=offset)
    return np.stack([table[a].astype(np.float64) for a in "xyz"], axis=1)


def _skip_binary_element(path: Path, data: bytes, offset: int, el: _PlyElement, endian: str) -> int:
    if all(c is None for _, _, c in el.properties):
        return offset + el.count * sum(np.dtype(_PLY_TYPES[t]).itemsize for _, t, _ in el.properties)
    for _ in range(el.count):  # list properties (faces before vertices: rare): walk item by item
        for _, typ, count_type in el.properties:
            size = np.dtype(_PLY_TYPES[typ]).itemsize
            if count_type is None:
                offset += size
            else:
                n = int(np.frombuffer(data, endian + _PLY_TYPES[count_type], 1, offset)[0])
                offset += np.dtype(_PLY_TYPES[count_type]).itemsize + n * size
    return offset


def write_ply_points(path: Path, points: np.ndarray, binary: bool = True) -> None:
    """Write points [N, 3] as a PLY point cloud (float32 binary little-endian, or ASCII)."""
    points = np.asarray(points, dtype=np.float32).reshape(-1, 3)
    header = (f"ply\nformat {'binary_little_endian' if binary else 'ascii'} 1.0\ncomment written by uw3dgs\n"
              f"element vertex {len(points)}\nproperty float x\nproperty float y\nproperty float z\nend_header\n")
    with open(path, "wb") as f:
        f.write(header.encode("ascii"))
        if binary:
            f.write(points.astype("<f4").tobytes())
        else:
            f.write("".join(" ".join(repr(float(v)) for v in p) + "\n" for p in points).encode("ascii"))


# ----------------------------------------------------------------------------------------------------
# Geometry evaluation


def distance_to_ground_truth(points: Tensor, gt_points: Tensor, max_block: int = 2**24,
                             return_index: bool = False) -> Tensor | tuple[Tensor, Tensor]:
    """Distance [N] from each point [N, 3] to its nearest ground-truth point [M, 3] (same frame and units).

    Brute force over blocks of query points (at most `max_block` distances, 64 MB, at once; ground-truth
    vertices, not the mesh's faces: a coarse mesh overestimates distances): the nearest point is chosen with a
    float32 matrix product on coordinates centred at the ground truth's mean (no cancellation far from
    the origin), and its distance recomputed exactly in float64. Runs on the points' device; on a CPU,
    300k Gaussians against 1M ground-truth points take minutes (use a GPU for that size).
    """
    if points.ndim != 2 or points.shape[-1] != 3 or gt_points.ndim != 2 or gt_points.shape[-1] != 3:
        raise ValueError(f"expected points [N, 3] and gt_points [M, 3], got {tuple(points.shape)} and "
                         f"{tuple(gt_points.shape)}")
    if len(gt_points) == 0:
        raise ValueError("no ground-truth points")
    device = points.device
    gt64 = gt_points.to(device=device, dtype=torch.float64)
    centre = gt64.mean(dim=0)
    gt32 = (gt64 - centre).float()
    chunk = max(1, max_block // len(gt_points))
    distances = torch.empty(len(points), dtype=torch.float64, device=device)
    indices = torch.empty(len(points), dtype=torch.long, device=device)
    for start in range(0, len(points), chunk):
        query64 = points[start : start + chunk].to(torch.float64)
        d2 = torch.cdist((query64 - centre).float(), gt32, compute_mode="use_mm_for_euclid_dist")
        nearest = d2.argmin(dim=1)
        indices[start : start + chunk] = nearest
        distances[start : start + chunk] = (query64 - gt64[nearest]).norm(dim=-1)
    result = distances.to(points.dtype if points.is_floating_point() else torch.float32)
    return (result, indices) if return_index else result


def umeyama(source: np.ndarray, target: np.ndarray, with_scale: bool = True) -> tuple[float, np.ndarray, np.ndarray]:
    """Similarity (s, R, t) minimising sum |target - (s R source + t)|^2 over corresponding points [N, 3]
    (Umeyama 1991); needs N >= 3 points not on one line."""
    source, target = np.asarray(source, dtype=np.float64), np.asarray(target, dtype=np.float64)
    if source.shape != target.shape or source.ndim != 2 or source.shape[1] != 3 or len(source) < 3:
        raise ValueError(f"umeyama needs two [N, 3] arrays of corresponding points, N >= 3; got {source.shape} "
                         f"and {target.shape}")
    mu_s, mu_t = source.mean(axis=0), target.mean(axis=0)
    xs, xt = source - mu_s, target - mu_t
    cov = xt.T @ xs / len(source)
    U, D, Vt = np.linalg.svd(cov)
    S = np.eye(3)
    if np.linalg.det(U) * np.linalg.det(Vt) < 0:
        S[2, 2] = -1.0
    R = U @ S @ Vt
    var_s = (xs**2).sum() / len(source)
    if var_s <= 0 or np.linalg.matrix_rank(xs, tol=1e-9 * max(1.0, np.abs(xs).max())) < 2:
        raise ValueError("umeyama: the source points are (nearly) collinear or identical; the alignment is undefined")
    s = float((D * np.diag(S)).sum() / var_s) if with_scale else 1.0
    t = mu_t - s * R @ mu_s
    return s, R, t


def apply_similarity(points: np.ndarray, s: float, R: np.ndarray, t: np.ndarray) -> np.ndarray:
    """s R x + t for points [N, 3]."""
    return s * np.asarray(points) @ np.asarray(R).T + np.asarray(t)


# ----------------------------------------------------------------------------------------------------
# Layout


def find_calib(root: Path) -> Path:
    calibs = sorted(p for p in Path(root).glob("*") if p.is_file() and p.suffix.lower() == ".calib")
    if not calibs:
        raise FileNotFoundError(f"{root}: no .calib stereo calibration file; a UWBundle folder holds one "
                                "(see docs/uwbundle.md)")
    if len(calibs) > 1:
        raise ValueError(f"{root}: several .calib files ({', '.join(p.name for p in calibs)}); keep exactly one")
    return calibs[0]


def _child(folder: Path, name: str) -> Path | None:
    """`folder/name`, matching the name case-insensitively (Left/, LEFT/, ...)."""
    if not folder.is_dir():
        return None
    found = [p for p in folder.iterdir() if p.is_dir() and p.name.lower() == name]
    return found[0] if found else None


def find_image_root(root: Path) -> Path:
    """The folder holding left/ and right/: ROOT or ROOT/images."""
    for base in (root, _child(root, "images")):
        if base is not None and _child(base, "left") and _child(base, "right"):
            return base
    raise FileNotFoundError(
        f"{root}: no left/ and right/ image folders (also looked in {root / 'images'}); put the left camera's "
        "images in left/ and the right camera's in right/, a stereo pair sharing a file name stem "
        "(see docs/uwbundle.md)"
    )


def stereo_images(image_root: Path) -> tuple[dict[str, str], list[tuple[str, str]]]:
    """Per image name (relative to image_root, as COLMAP names them) its side, and the stereo pairs
    (left name, right name) matched by file stem."""
    sides: dict[str, str] = {}
    stems: dict[str, dict[str, str]] = {side: {} for side in SIDES}
    for side in SIDES:
        folder = _child(image_root, side)
        assert folder is not None
        for rel in list_images(folder):
            name = f"{folder.name}/{rel}"
            sides[name] = side
            stems[side][str(Path(rel).with_suffix(""))] = name
    if not any(v == "left" for v in sides.values()) or not any(v == "right" for v in sides.values()):
        raise FileNotFoundError(f"{image_root}: left/ or right/ holds no image ({', '.join(IMAGE_EXTENSIONS)})")
    pairs = [(stems["left"][s], stems["right"][s]) for s in sorted(stems["left"].keys() & stems["right"].keys())]
    return sides, pairs


# ----------------------------------------------------------------------------------------------------
# Structure from motion, scaled by the stereo baseline, cached


@dataclass
class StereoCheck:
    """How well the SfM poses agree with the calibration, over the stereo pairs both registered."""

    pairs: int
    scale: float
    """Factor from SfM units to calibration units (median calibrated baseline / SfM baseline)."""
    baseline_spread: float
    """Relative spread (std / median) of the per-pair SfM baselines: 0 for a perfectly rigid rig."""
    rotation_error_deg: float
    """Median angle between the SfM and calibrated right-from-left rotations."""


def check_stereo(rec: pycolmap.Reconstruction, pairs: list[tuple[str, str]], calib: StereoCalibration) -> StereoCheck:
    by_name = {im.name: im for im in rec.images.values() if im.has_pose}
    R_cal, _ = calib.right_from_left()
    ratios, angles = [], []
    for left, right in pairs:
        if left in by_name and right in by_name:
            pl, pr = by_name[left].cam_from_world(), by_name[right].cam_from_world()
            rel = pr * pl.inverse()  # right from left
            ratios.append(float(np.linalg.norm(rel.translation)))
            dR = rel.rotation.matrix() @ R_cal.T
            angles.append(float(np.degrees(np.arccos(np.clip((np.trace(dR) - 1) / 2, -1, 1)))))
    if not ratios:
        return StereoCheck(0, 1.0, float("nan"), float("nan"))
    sfm_baselines = np.array(ratios)
    median = float(np.median(sfm_baselines))
    return StereoCheck(len(ratios), calib.baseline / median, float(sfm_baselines.std() / median),
                       float(np.median(angles)))


def sfm_cache_key(calib_path: Path, image_root: Path, names: list[str], matcher: str) -> str:
    """Hash of what the model depends on: the calibration, the image files (names and sizes) and the recipe."""
    files = [(n, (image_root / n).stat().st_size) for n in names]
    payload = {"version": SFM_VERSION, "calib": hashlib.sha256(calib_path.read_bytes()).hexdigest(),
               "images": files, "matcher": matcher}
    return hashlib.sha256(json.dumps(payload, sort_keys=True).encode()).hexdigest()[:16]


def _writable(folder: Path) -> bool:
    """Whether files can be created in `folder` (tried for real: permission bits lie on some mounts)."""
    probe = folder / f".uw3dgs-write-test-{uuid.uuid4().hex}"
    try:
        probe.write_bytes(b"")
        probe.unlink()
        return True
    except OSError:
        return False


def _read_stamp(sparse_parent: Path) -> dict | None:
    try:
        return json.loads((sparse_parent / STAMP).read_text())
    except (OSError, ValueError):
        return None


def ensure_model(root: Path, calib: StereoCalibration, image_root: Path, matcher: str, cache_dir: Path | None,
                 progress: bool = True) -> Path:
    """The COLMAP model folder of this dataset: the user's ROOT/sparse/0 if there is one, else a cached
    SfM result for the current images and calibration, else a new SfM run (cached)."""
    assert calib.path is not None
    user_model = root / "sparse" / "0"
    stamp = _read_stamp(root / "sparse")
    if user_model.is_dir() and stamp is None:
        return user_model  # a model the user made (COLMAP, Metashape export, ...): use it as it is
    sides, pairs = stereo_images(image_root)
    names = sorted(sides)
    key = sfm_cache_key(calib.path, image_root, names, matcher)
    cache_parent = (cache_dir or default_cache_dir()) / "uwbundle" / (
        f"{root.resolve().name}-{hashlib.sha256(str(root.resolve()).encode()).hexdigest()[:8]}")
    for parent in (root / "sparse", cache_parent / "sparse"):
        found = _read_stamp(parent)
        if found is not None and found.get("key") == key and (parent / "0").is_dir():
            return parent / "0"
    # First use (or the images / calibration changed): structure from motion with fixed intrinsics.
    cameras = {}
    for side, cam in (("left", calib.left), ("right", calib.right)):
        folder = next(n.split("/")[0] for n, s in sides.items() if s == side)
        fixed = cam.fixed_camera()
        size = _first_image_size(image_root, [n for n, s in sides.items() if s == side])
        if size != (fixed.width, fixed.height):
            fixed = fixed.rescaled(*size)  # images resized after calibration (same aspect ratio)
            print(f"uw3dgs: {side} images are {size[0]}x{size[1]}, the calibration is for {cam.width}x{cam.height}; "
                  "intrinsics rescaled to match", file=sys.stderr)
        cameras[folder] = fixed
    print(f"uw3dgs: {root.name}: no camera poses yet; running structure from motion on {len(names)} images "
          f"({len(pairs)} stereo pairs) with the calibrated intrinsics. This happens once; the model is cached.",
          file=sys.stderr)
    start = time.perf_counter()
    in_dataset = _writable(root) and (stamp is not None or not user_model.exists())
    target_parent = root / "sparse" if in_dataset else cache_parent / "sparse"
    target_parent.parent.mkdir(parents=True, exist_ok=True)
    work = Path(tempfile.mkdtemp(prefix=".sfm-", dir=target_parent.parent))
    try:
        sparse = run_sfm(image_root, work, cameras, matcher=matcher, progress=progress,
                         sequence_key=lambda name: str(Path(name.split("/", 1)[1]).with_suffix("")),
                         quality_check=lambda rec: stereo_badness(check_stereo(rec, pairs, calib)))
        rec = pycolmap.Reconstruction(str(sparse))
        check = check_stereo(rec, pairs, calib)
        if check.pairs:
            rec.transform(pycolmap.Sim3d(check.scale, pycolmap.Rotation3d(), np.zeros(3)))
        _warn_stereo(check, calib, target_parent / "0")
        out = work / "out"
        (out / "0").mkdir(parents=True)
        rec.write_binary(str(out / "0"))
        stats = {"key": key, "registered": rec.num_reg_images(), "images": len(names), "points": rec.num_points3D(),
                 "seconds": round(time.perf_counter() - start, 1), "matcher": matcher, "stereo_pairs_used": check.pairs,
                 "scale_to_calibration_units": check.scale, "baseline_spread": check.baseline_spread,
                 "stereo_rotation_error_deg": check.rotation_error_deg, "sfm_version": SFM_VERSION}
        (out / STAMP).write_text(json.dumps(stats, indent=2) + "\n")
        # Model and stamp appear together (a rename): a killed run never leaves a stamp-less model that a
        # later load would take for the user's own.
        if _read_stamp(target_parent) is not None:
            shutil.rmtree(target_parent)  # our own stale model (images or calibration changed)
        os.replace(out, target_parent)
    finally:
        shutil.rmtree(work, ignore_errors=True)
    return target_parent / "0"


def _first_image_size(image_root: Path, names: list[str]) -> tuple[int, int]:
    return image_size(image_root / sorted(names)[0])


MAX_BASELINE_SPREAD = 0.1
"""A rigid rig's SfM baselines should agree within this relative spread (measured 2% on the test capture;
a model in a wrong local minimum showed 35%)."""
MAX_ROTATION_ERROR_DEG = 3.0


def stereo_badness(check: StereoCheck) -> tuple[float, str]:
    """(badness, why) for run_sfm's quality_check: above 1 when the SfM stereo pairs contradict the calibration."""
    if not check.pairs:
        return 0.0, ""
    badness = max(check.baseline_spread / MAX_BASELINE_SPREAD, check.rotation_error_deg / MAX_ROTATION_ERROR_DEG)
    return badness, (f"stereo baselines vary by {100 * check.baseline_spread:.0f}% and the left-right rotation is off "
                     f"by {check.rotation_error_deg:.1f} deg")


def _warn_stereo(check: StereoCheck, calib: StereoCalibration, model: Path) -> None:
    if not check.pairs:
        print(f"uw3dgs: warning: no stereo pair registered with both images; the model keeps SfM's arbitrary "
              f"scale instead of {calib.path}'s units", file=sys.stderr)
        return
    if stereo_badness(check)[0] > 1.0:
        print(f"uw3dgs: warning: the SfM poses disagree with {calib.path} over {check.pairs} stereo pairs "
              f"(baseline spread {100 * check.baseline_spread:.0f}%, rotation off by {check.rotation_error_deg:.1f} "
              "deg): the model is probably wrong. Structure from motion may have settled in a wrong local minimum "
              "(try --datamanager.matcher sequential, or more images), left/ and right/ may be swapped, or the "
              f"calibration may be another rig's. Delete {model.parent} to run it again.", file=sys.stderr)


def load_model_scene(root: Path, image_root: Path, sparse_dir: Path, cache_dir: Path | None,
                     downscale_factor: int = 1) -> SceneData:
    """read_colmap_dataset on the model. Camera models that reader cannot undistort (FULL_OPENCV, used when
    the calibration has k3 != 0) are undistorted by COLMAP first (pycolmap.undistort_images), once, into
    the cache: <cache_dir>/uwbundle/undistorted-<hash of the model and image folder>/."""
    rec = pycolmap.Reconstruction(str(sparse_dir))
    if all(c.model_name in colmap_dataset.SUPPORTED_CAMERA_MODELS for c in rec.cameras.values()):
        return colmap_dataset.read_colmap_dataset(root, image_root, sparse_dir, cache_dir, downscale_factor)
    digest = hashlib.sha256(str(image_root.resolve()).encode())
    for path in sorted(sparse_dir.iterdir()):
        digest.update(path.name.encode() + path.read_bytes())
    undistorted = (cache_dir or default_cache_dir()) / "uwbundle" / f"undistorted-{digest.hexdigest()[:16]}"
    if not (undistorted / "sparse").is_dir():
        undistorted.parent.mkdir(parents=True, exist_ok=True)
        tmp = Path(tempfile.mkdtemp(prefix=".undistort-", dir=undistorted.parent))
        try:
            with quiet_colmap():
                pycolmap.undistort_images(str(tmp), str(sparse_dir), str(image_root))
            shutil.rmtree(undistorted, ignore_errors=True)
            tmp.rename(undistorted)  # atomic: a killed run leaves no half-undistorted folder behind
        finally:
            shutil.rmtree(tmp, ignore_errors=True)
    return colmap_dataset.read_colmap_dataset(root, undistorted / "images", undistorted / "sparse", cache_dir,
                                              downscale_factor)


def find_ground_truth(root: Path) -> Path | None:
    found = [p for p in Path(root).iterdir() if p.is_file() and p.name.lower() == "groundtruth.ply"]
    return found[0] if found else None


def read_uwbundle(root: Path, matcher: str = "exhaustive", cache_dir: Path | None = None, downscale_factor: int = 1,
                  normalize: bool = True, progress: bool = True) -> SceneData:
    """A UWBundle folder as one SceneData (running and caching structure from motion on first use)."""
    root = Path(root)
    calib = read_calib(find_calib(root))
    image_root = find_image_root(root)
    sparse_dir = ensure_model(root, calib, image_root, matcher, cache_dir, progress)
    scene = load_model_scene(root, image_root, sparse_dir, cache_dir, downscale_factor)
    if normalize:
        scene = colmap_dataset.normalize_scene(scene)
    gt_path = find_ground_truth(root)
    if gt_path is not None:
        scene = replace(scene, gt_points=torch.from_numpy(read_ply_points(gt_path)).float())
    return scene


# ----------------------------------------------------------------------------------------------------
# The datamanager


@dataclass(frozen=True)
class UWBundleDataManagerConfig(DataManagerConfig):
    _target: Target = target(lambda: UWBundleDataManager)
    matcher: Literal["exhaustive", "sequential"] = "exhaustive"
    """First-use SfM matching: exhaustive (every pair, up to a few hundred images) or sequential (by file name)."""
    cache_dir: Path | None = None
    """Processed images, and SfM models of read-only datasets; default $UW3DGS_CACHE or ~/.cache/uw3dgs."""
    normalize: bool = True
    """Centre on the cameras, median point distance 1 (recorded in the run); dataset units are the .calib's."""

    @classmethod
    def can_read(cls, path: Path) -> bool:
        """A folder holding a .calib stereo calibration file."""
        return path.is_dir() and any(p.suffix.lower() == ".calib" and p.is_file() for p in path.iterdir())


class UWBundleDataManager(DataManager):
    config: UWBundleDataManagerConfig
    downscales_on_load = True

    def load_scene(self, data: Path | None) -> SceneData:
        if data is None:
            raise ValueError("the uwbundle datamanager needs --data: a folder with a .calib file and left/, right/ "
                             "image folders (see docs/uwbundle.md)")
        return read_uwbundle(Path(data), self.config.matcher, self.config.cache_dir, self.downscale_factor,
                             normalize=self.config.normalize)


datamanager = DataManagerSpec(
    "uwbundle", "UWBundle stereo captures (.calib + left/ right/ images + groundtruth.ply); structure from motion "
    "with the calibrated intrinsics runs once on first use.", UWBundleDataManagerConfig())
