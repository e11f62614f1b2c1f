"""The nerfstudio / instant-ngp `transforms.json` layout, read into the same `ColmapModel` the COLMAP reader uses.

    ROOT/transforms.json   cameras and poses (below); image paths are relative to ROOT
    ROOT/<images>          the images it names (any subfolder, e.g. images/frame_00001.png)
    ROOT/<ply_file_path>   optional initial points (nerfstudio's sparse_pc.ply: x, y, z, red, green, blue)

transforms.json: intrinsics at the top level, each overridable per frame (`fl_x`, `fl_y`, `cx`, `cy`, `w`, `h`,
distortion `k1`, `k2`, `k3`, `k4`, `p1`, `p2`, `camera_model`; `camera_angle_x` when `fl_x` is missing, as
instant-ngp and Blender files have), and `frames`: [{`file_path`, `transform_matrix`}, ...]. The pixel
convention is COLMAP's (pixel centres at +0.5: ns-process-data copies COLMAP's cx, cy unchanged).

Poses. `transform_matrix` is camera-to-world in the OpenGL/Blender camera convention (x right, y up, z back);
uw3dgs' cameras are OpenCV's (x right, y down, z forward, world-to-camera), so

    viewmat = inverse(transform_matrix @ diag(1, -1, -1, 1)).

The world frame is the file's own (nerfstudio's processing swaps and flips world axes, `applied_transform`):
any rigid world frame is fine, the scene is normalised afterwards, and `ply_file_path` points are in the
same frame as the poses.

Camera models: PINHOLE / SIMPLE_PINHOLE, and OPENCV (k1, k2, p1, p2), undistorted by the COLMAP reader
(`uw3dgs.data.colmap_dataset`). OPENCV with k3 or k4 non-zero, OPENCV_FISHEYE and EQUIRECTANGULAR are refused
with a one-line error (undistort the images first).

Split: `train_filenames` and `test_filenames` (or `val_filenames` when there is no test list) when the file
carries them; the views in neither list are left out.
"""

from __future__ import annotations

import json
import math
import os
from dataclasses import dataclass
from pathlib import Path, PurePosixPath

import numpy as np
import pycolmap

from uw3dgs.data.colmap_dataset import ColmapModel, DatasetError
from uw3dgs.data.ply import read_ply_vertices
from uw3dgs.utils.console import warn
from uw3dgs.utils.images import image_size

TRANSFORMS_FILE = "transforms.json"
OPENGL_TO_OPENCV = np.diag([1.0, -1.0, -1.0, 1.0])
"""Right-multiplied onto an OpenGL camera-to-world matrix: flips the camera's y and z axes."""
INTRINSIC_KEYS = ("fl_x", "fl_y", "cx", "cy", "w", "h", "k1", "k2", "k3", "k4", "p1", "p2", "camera_model",
                  "camera_angle_x", "camera_angle_y")
PINHOLE_NAMES = ("PINHOLE", "SIMPLE_PINHOLE")
IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg", ".JPG", ".PNG", ".JPEG")


@dataclass
class TransformsScene:
    """A transforms.json read: the model (views sorted by name), where the images are, the split it carries."""

    model: ColmapModel
    image_dir: Path
    """The folder the names in `model.names` are relative to."""
    split: tuple[list[int], list[int]] | None
    """(train, test) view indices into `model.names`, or None when the file names no split."""
    has_points: bool


def opengl_c2w_to_viewmat(c2w: np.ndarray) -> np.ndarray:
    """World-to-camera [4, 4] in OpenCV axes from a camera-to-world [3, 4] or [4, 4] in OpenGL axes."""
    c2w = np.asarray(c2w, dtype=np.float64)
    full = np.eye(4)
    full[: c2w.shape[0]] = c2w
    return np.linalg.inv(full @ OPENGL_TO_OPENCV)


def viewmat_to_opengl_c2w(viewmat: np.ndarray) -> np.ndarray:
    """The inverse of `opengl_c2w_to_viewmat`: what transforms.json stores for an OpenCV world-to-camera pose."""
    return np.linalg.inv(np.asarray(viewmat, dtype=np.float64)) @ OPENGL_TO_OPENCV


def frame_camera(meta: dict, frame: dict, path: Path, image_path: Path) -> pycolmap.Camera:
    """The COLMAP camera of one frame: its own intrinsics where it has them, the file's otherwise."""
    values = {key: frame.get(key, meta.get(key)) for key in INTRINSIC_KEYS}
    model = str(values["camera_model"] or "OPENCV").upper()
    if values["w"] is None or values["h"] is None:
        values["w"], values["h"] = image_size(image_path)
    width, height = int(values["w"]), int(values["h"])
    fx, fy = values["fl_x"], values["fl_y"]
    if fx is None and values["camera_angle_x"] is not None:
        fx = 0.5 * width / math.tan(0.5 * float(values["camera_angle_x"]))
    if fy is None and values["camera_angle_y"] is not None:
        fy = 0.5 * height / math.tan(0.5 * float(values["camera_angle_y"]))
    if fx is None:
        raise DatasetError(f"{path}: frame {frame.get('file_path')} has no focal length (fl_x or camera_angle_x, "
                           "at the top level or in the frame); add it, or pose the images with `uw-process-data`")
    fx = float(fx)
    fy = fx if fy is None else float(fy)
    cx = 0.5 * width if values["cx"] is None else float(values["cx"])
    cy = 0.5 * height if values["cy"] is None else float(values["cy"])
    k1, k2, k3, k4, p1, p2 = (float(values[k] or 0.0) for k in ("k1", "k2", "k3", "k4", "p1", "p2"))
    if model == "OPENCV" and (k3 or k4):
        raise DatasetError(f"{path}: frame {frame.get('file_path')} has k3/k4 distortion (k3={k3}, k4={k4}), which "
                           "uw3dgs does not undistort; undistort the images first (`colmap image_undistorter`, "
                           "then read its output with the colmap datamanager)")
    if model == "OPENCV" and (k1 or k2 or p1 or p2):
        return pycolmap.Camera(model="OPENCV", width=width, height=height, params=[fx, fy, cx, cy, k1, k2, p1, p2])
    if model in ("OPENCV", *PINHOLE_NAMES):
        return pycolmap.Camera(model="PINHOLE", width=width, height=height, params=[fx, fy, cx, cy])
    raise DatasetError(f"{path}: camera_model {model} (frame {frame.get('file_path')}) is not supported (supported: "
                       "OPENCV with k1, k2, p1, p2; PINHOLE; SIMPLE_PINHOLE); undistort the images to a pinhole "
                       "camera first")


def resolve_image(root: Path, file_path: str, path: Path) -> Path:
    """The image a frame's `file_path` names (relative to ROOT; Blender-style paths without a suffix too);
    FileNotFoundError if there is none."""
    image = (root / file_path).resolve()
    if image.is_file():
        return image
    for suffix in IMAGE_SUFFIXES:
        if image.with_name(image.name + suffix).is_file():
            return image.with_name(image.name + suffix)
    raise FileNotFoundError(f"{root / file_path}: image missing ({path} lists it); restore it, or remove its "
                            "frame from the file")


def read_transforms(root: Path) -> TransformsScene:
    """ROOT/transforms.json as a `ColmapModel` (points only from `ply_file_path`; none otherwise) and its split."""
    root = Path(root)
    path = root / TRANSFORMS_FILE
    if not path.is_file():
        raise FileNotFoundError(f"{path}: missing; the nerfstudio datamanager reads a folder with transforms.json "
                                "(ns-process-data's output), or pose plain images with `uw-process-data --images DIR`")
    try:
        meta = json.loads(path.read_text())
    except (OSError, ValueError) as err:
        raise DatasetError(f"{path}: cannot read it as JSON ({err}); re-export it") from err
    frames = meta.get("frames") if isinstance(meta, dict) else None
    if not frames:
        raise DatasetError(f"{path}: no 'frames' list; a transforms.json names each image and its pose in 'frames'")
    views, missing = [], []
    for frame in frames:
        if "file_path" not in frame or "transform_matrix" not in frame:
            raise DatasetError(f"{path}: a frame without 'file_path' or 'transform_matrix' ({frame}); every frame "
                               "needs both")
        matrix = np.asarray(frame["transform_matrix"], dtype=np.float64)
        if matrix.shape not in ((3, 4), (4, 4)) or not np.isfinite(matrix).all():
            raise DatasetError(f"{path}: frame {frame['file_path']} has a transform_matrix of shape {matrix.shape} "
                               "or with non-finite values; it must be a 4x4 (or 3x4) camera-to-world matrix")
        try:
            image = resolve_image(root, frame["file_path"], path)
        except FileNotFoundError:
            missing.append(str(frame["file_path"]))
            continue
        views.append((image, frame_camera(meta, frame, path, image), opengl_c2w_to_viewmat(matrix)))
    if missing:  # e.g. instant-ngp's fox: its file lists 67 frames, its repository ships 50 of the images
        shown = ", ".join(missing[:3]) + (", ..." if len(missing) > 3 else "")
        if not views:
            raise FileNotFoundError(f"{path}: none of its {len(missing)} frames' images exists (first: {shown}); "
                                    "restore the images beside the file")
        warn(f"{path}: {len(missing)} of its {len(frames)} frames name images that are not there ({shown}); "
             f"training on the {len(views)} that are")
    views.sort(key=lambda view: str(view[0]))
    image_dir = Path(os.path.commonpath([str(v[0].parent) for v in views]))
    names = [str(PurePosixPath(*v[0].relative_to(image_dir).parts)) for v in views]
    points, colors = read_points(root, meta, path)
    return TransformsScene(
        model=ColmapModel(names=names, cameras=[v[1] for v in views], viewmats=np.stack([v[2] for v in views]),
                          points=points, colors=colors, cameras_file=path, images_file=path),
        image_dir=image_dir,
        split=read_split(root, meta, path, [v[0] for v in views]),
        has_points=len(points) > 0,
    )


def read_points(root: Path, meta: dict, path: Path) -> tuple[np.ndarray, np.ndarray]:
    """([P, 3] float64, [P, 3] uint8) from `ply_file_path` (grey without red/green/blue); empty without one."""
    if not meta.get("ply_file_path"):
        return np.zeros((0, 3)), np.zeros((0, 3), dtype=np.uint8)
    ply = root / meta["ply_file_path"]
    if not ply.is_file():
        raise FileNotFoundError(f"{ply}: missing ({path} names it as ply_file_path); restore it, or remove "
                                "ply_file_path from the file to start from random points")
    vertex = read_ply_vertices(ply)
    points = np.stack([vertex[a] for a in "xyz"], axis=1)
    if all(c in vertex for c in ("red", "green", "blue")):
        colors = np.stack([vertex[c] for c in ("red", "green", "blue")], axis=1)
    else:
        colors = np.full_like(points, 128.0)
    return points, np.clip(np.rint(colors), 0, 255).astype(np.uint8)


def read_split(root: Path, meta: dict, path: Path, images: list[Path]) -> tuple[list[int], list[int]] | None:
    """(train, test) indices from train_filenames and test_filenames (val_filenames without a test list)."""
    if "train_filenames" not in meta:
        return None
    test_key = "test_filenames" if "test_filenames" in meta else "val_filenames"
    index = {image: k for k, image in enumerate(images)}
    split = []
    for key in ("train_filenames", test_key):
        indices = []
        for name in meta.get(key, []):
            found = index.get(resolve_image(root, name, path))
            if found is None:
                raise DatasetError(f"{path}: {key} names {name}, which no frame has; fix the list or add the frame")
            indices.append(found)
        split.append(sorted(indices))
    if set(split[0]) & set(split[1]):
        raise DatasetError(f"{path}: train_filenames and {test_key} share views; a view is either trained on or "
                           "held out")
    return split[0], split[1]


def random_points(viewmats: np.ndarray, count: int, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """Initial points without SfM points: uniform in the cube centred on the mean camera centre whose half-side
    is the cameras' largest distance from it (the cameras' bounds), grey. Returns ([P, 3], [P, 3] uint8)."""
    centers = np.stack([-v[:3, :3].T @ v[:3, 3] for v in viewmats])
    middle = centers.mean(axis=0)
    half = max(float(np.linalg.norm(centers - middle, axis=1).max()), 1e-6)
    rng = np.random.default_rng(seed)
    points = rng.uniform(middle - half, middle + half, (count, 3))
    return points, np.full((count, 3), 128, dtype=np.uint8)
