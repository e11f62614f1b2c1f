"""Reader of the SeaThru-NeRF on-disk layout, which the synthetic scene generator also writes.

    ROOT/Images_wb/ (or images_wb/)  8-bit PNG/JPG images
    ROOT/sparse/0/                   COLMAP model: cameras, images (world-to-camera poses), points3D
    ROOT/poses_bounds.npy            optional: LLFF poses and per-image near/far z-depth bounds
    ROOT/gt/                         optional (synthetic scenes): clean/*.png, range/*.npy, medium.json

Views are sorted by file name (the SeaThru-NeRF split relies on it). This version reads undistorted
pinhole cameras only; undistortion of real data comes with the seathru-nerf datamanager.
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pycolmap
import torch
from PIL import Image

from uw3dgs.cameras import Camera
from uw3dgs.data.scene import GroundTruth, SceneData

IMAGE_DIRS = ("Images_wb", "images_wb")
SUPPORTED_CAMERA_MODELS = ("PINHOLE", "SIMPLE_PINHOLE")
EIGHT_BIT_MODES = ("1", "L", "LA", "P", "RGB", "RGBA", "CMYK", "YCbCr")


@dataclass
class ColmapModel:
    """The parts of a COLMAP reconstruction a scene needs, views sorted by image name."""

    names: list[str]
    viewmats: np.ndarray
    """[N, 4, 4] world-to-camera."""
    intrinsics: np.ndarray
    """[N, 3, 3] K of each view's camera."""
    sizes: list[tuple[int, int]]
    """(width, height) of each view's camera."""
    points: np.ndarray
    """[P, 3] point positions."""
    colors: np.ndarray
    """[P, 3] uint8 point colours."""


def find_image_dir(root: Path) -> Path:
    """`Images_wb/` as the dataset ships it, or `images_wb/`."""
    for name in IMAGE_DIRS:
        if (root / name).is_dir():
            return root / name
    raise FileNotFoundError(
        f"{root}: no image folder ({' or '.join(IMAGE_DIRS)}); point --data at a SeaThru-NeRF scene "
        "folder, or write one with `uw-synth --out DIR`"
    )


def _model_file(sparse_dir: Path, stem: str) -> Path:
    """cameras.bin or cameras.txt (whichever COLMAP wrote), for error messages."""
    binary, text = sparse_dir / f"{stem}.bin", sparse_dir / f"{stem}.txt"
    return text if text.exists() and not binary.exists() else binary


def _check_camera_model(camera: pycolmap.Camera, sparse_dir: Path) -> None:
    if camera.model_name not in SUPPORTED_CAMERA_MODELS:
        raise ValueError(
            f"{_model_file(sparse_dir, 'cameras')}: camera {camera.camera_id} has model {camera.model_name}; "
            f"this reader supports undistorted cameras only ({', '.join(SUPPORTED_CAMERA_MODELS)}). "
            "Undistortion of real data comes with the seathru-nerf datamanager."
        )


def read_colmap_model(sparse_dir: Path) -> ColmapModel:
    """Registered images (sorted by name) with poses and intrinsics, and the 3D points with colours."""
    if not sparse_dir.is_dir():
        raise FileNotFoundError(
            f"{sparse_dir}: no COLMAP model; run COLMAP (or pycolmap) structure from motion on the images "
            "and put the model there, or write a scene with `uw-synth --out DIR`"
        )
    try:
        rec = pycolmap.Reconstruction(str(sparse_dir))
    except Exception as err:  # pycolmap raises bare RuntimeErrors on missing or corrupt files
        raise ValueError(f"{sparse_dir}: cannot read the COLMAP model ({err})") from err
    for camera in rec.cameras.values():
        _check_camera_model(camera, sparse_dir)
    images = sorted((im for im in rec.images.values() if im.has_pose), key=lambda im: im.name)
    if not images:
        raise ValueError(f"{_model_file(sparse_dir, 'images')}: no registered image with a pose")
    viewmats = np.tile(np.eye(4), (len(images), 1, 1))
    for k, image in enumerate(images):
        viewmats[k, :3] = image.cam_from_world().matrix()
    cameras = [rec.cameras[im.camera_id] for im in images]
    point_ids = sorted(rec.points3D)
    return ColmapModel(
        names=[im.name for im in images],
        viewmats=viewmats,
        intrinsics=np.stack([cam.calibration_matrix() for cam in cameras]),
        sizes=[(cam.width, cam.height) for cam in cameras],
        points=np.array([rec.points3D[i].xyz for i in point_ids]).reshape(-1, 3),
        colors=np.array([rec.points3D[i].color for i in point_ids], dtype=np.uint8).reshape(-1, 3),
    )


def _read_image(path: Path, hint: str) -> np.ndarray:
    """One 8-bit image as float32 [H, W, 3] in [0, 1], with an error naming the file if it is unusable."""
    if not path.is_file():
        raise FileNotFoundError(f"{path}: image missing; {hint}")
    try:
        with Image.open(path) as img:
            if img.mode not in EIGHT_BIT_MODES:
                raise ValueError(f"{path}: mode {img.mode} is not 8-bit; convert it to 8-bit PNG or JPG")
            pixels = np.asarray(img.convert("RGB"))
    except (OSError, SyntaxError) as err:  # PIL's errors for truncated or corrupt files
        raise ValueError(f"{path}: unreadable image ({err}); re-export or restore it") from err
    return pixels.astype(np.float32) / 255.0


def load_images(image_dir: Path, names: list[str], hint: str) -> np.ndarray:
    """Images [N, H, W, 3] float32 in [0, 1]; all must have one size. `hint` says what to do if one is
    missing."""
    images = []
    for name in names:
        pixels = _read_image(image_dir / name, hint)
        if images and pixels.shape != images[0].shape:
            (h0, w0), (h, w) = images[0].shape[:2], pixels.shape[:2]
            raise ValueError(
                f"{image_dir / name}: mixed image sizes, {w}x{h} here but {w0}x{h0} for "
                f"{image_dir / names[0]}; resize or undistort all images to one size"
            )
        images.append(pixels)
    return np.stack(images)


def read_poses_bounds(path: Path, num_views: int) -> np.ndarray:
    """Per-view (near, far) camera z-depth bounds [N, 2] from LLFF's poses_bounds.npy."""
    rows = np.load(path)
    if rows.ndim != 2 or rows.shape[1] != 17:
        raise ValueError(f"{path}: expected LLFF rows of 17 numbers, got shape {rows.shape}")
    if len(rows) != num_views:
        raise ValueError(f"{path}: {len(rows)} rows for {num_views} posed images; need one row per image")
    return rows[:, 15:17]


def z_bounds_from_points(points: np.ndarray, viewmats: np.ndarray, intrinsics: np.ndarray,
                         sizes: list[tuple[int, int]]) -> np.ndarray:
    """Per-view (near, far) z-depths of the points each view sees, LLFF's 0.1 / 99.9 percentiles."""
    bounds = []
    for viewmat, K, (width, height) in zip(viewmats, intrinsics, sizes, strict=True):
        cam = points @ viewmat[:3, :3].T + viewmat[:3, 3]
        z = cam[:, 2]
        front = z > 1e-6
        uv = cam[front] @ K.T
        uv = uv[:, :2] / uv[:, 2:]
        inside = (uv[:, 0] >= 0) & (uv[:, 0] <= width) & (uv[:, 1] >= 0) & (uv[:, 1] <= height)
        if inside.any():
            bounds.append(np.percentile(z[front][inside], [0.1, 99.9]))
    if not bounds:
        raise ValueError("no poses_bounds.npy and no 3D point inside any view: cannot set near/far")
    return np.stack(bounds)


def range_bounds(
    z_bounds: np.ndarray, intrinsics: np.ndarray, sizes: list[tuple[int, int]]
) -> tuple[float, float]:
    """Scene near/far along the rays from per-view z-depth bounds: range >= z everywhere, and the range
    of a point at z-depth z is at most z times the ray-length factor |K^-1 (u, v, 1)| of an image corner."""
    corner_factor = 1.0
    for K, (width, height) in zip(intrinsics, sizes, strict=True):
        corners = np.array([[0, 0, 1], [width, 0, 1], [0, height, 1], [width, height, 1]], dtype=float)
        corner_factor = max(corner_factor, float(np.linalg.norm(corners @ np.linalg.inv(K).T, axis=1).max()))
    return float(z_bounds[:, 0].min()), float(z_bounds[:, 1].max()) * corner_factor


def read_ground_truth(gt_dir: Path, names: list[str]) -> GroundTruth:
    """Clean images gt/clean/<name>, ranges gt/range/<stem>.npy and gt/medium.json of a synthetic scene."""
    hint = "gt/ must hold one clean image and one range map per image; regenerate the scene with uw-synth"
    clean = load_images(gt_dir / "clean", names, hint)
    ranges = []
    for name in names:
        path = gt_dir / "range" / Path(name).with_suffix(".npy")
        if not path.is_file():
            raise FileNotFoundError(f"{path}: range map missing; {hint}")
        r = np.load(path).astype(np.float32)
        if r.shape != clean.shape[1:3]:
            raise ValueError(f"{path}: shape {r.shape} but the images are {clean.shape[1:3]}; {hint}")
        ranges.append(r)
    medium_path = gt_dir / "medium.json"
    if not medium_path.is_file():
        raise FileNotFoundError(f"{medium_path}: medium parameters missing; {hint}")
    medium = json.loads(medium_path.read_text())
    return GroundTruth(torch.from_numpy(clean), torch.from_numpy(np.stack(ranges)), medium)


def read_seathru_layout(root: Path) -> SceneData:
    """A scene folder in the SeaThru-NeRF layout (plus gt/ when present) as one SceneData."""
    root = Path(root)
    image_dir = find_image_dir(root)
    sparse_dir = root / "sparse" / "0"
    model = read_colmap_model(sparse_dir)
    hint = f"{_model_file(sparse_dir, 'images')} lists it; restore the image or remove it from the model"
    images = load_images(image_dir, model.names, hint)
    height, width = images.shape[1:3]
    for name, size in zip(model.names, model.sizes, strict=True):
        if size != (width, height):
            raise ValueError(
                f"{image_dir / name}: {width}x{height} pixels but its camera in "
                f"{_model_file(sparse_dir, 'cameras')} is {size[0]}x{size[1]}; images and model must match"
            )
    bounds_path = root / "poses_bounds.npy"
    if bounds_path.is_file():
        z_bounds = read_poses_bounds(bounds_path, len(model.names))
    else:
        z_bounds = z_bounds_from_points(model.points, model.viewmats, model.intrinsics, model.sizes)
    near, far = range_bounds(z_bounds, model.intrinsics, model.sizes)
    viewmats = torch.tensor(model.viewmats, dtype=torch.float32)
    intrinsics = torch.tensor(model.intrinsics, dtype=torch.float32)
    views = zip(viewmats, intrinsics, model.names, strict=True)
    cameras = [Camera(M, K, width, height, name) for M, K, name in views]
    gt_dir = root / "gt"
    return SceneData(
        name=root.name,
        image_names=model.names,
        images=torch.from_numpy(images),
        cameras=cameras,
        points=torch.tensor(model.points, dtype=torch.float32),
        point_colors=torch.tensor(model.colors, dtype=torch.float32) / 255.0,
        near=near,
        far=far,
        gt=read_ground_truth(gt_dir, model.names) if gt_dir.is_dir() else None,
    )
