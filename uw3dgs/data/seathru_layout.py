"""The SeaThru-NeRF on-disk layout (real scenes, and the synthetic scenes `uw-synth` writes).

    ROOT/Images_wb/ (or images_wb/)  8-bit PNG/JPG images
    ROOT/sparse/0/                   COLMAP model: cameras, images (world-to-camera poses), points3D
    ROOT/poses_bounds.npy            LLFF poses and per-image near/far z-depth bounds
    ROOT/gt/                         optional (synthetic scenes): clean/*.png, range/*.npy, medium.json

At least one of sparse/0 and poses_bounds.npy must be there. Pixels, cameras, undistortion, downscaling
and the image cache all go through `uw3dgs.data.colmap_dataset` (one reading path for every layout);
this module adds what is specific to the layout: the image folder's name, LLFF poses and bounds, the
choice between the two pose sources when both are present, and the synthetic scenes' ground truth.

Pose sources (`poses`): 'colmap' (sparse/0/images.bin), 'llff' (poses_bounds.npy), or 'auto': the only
one present; when both are present and agree, COLMAP's; when they disagree, the one under which the
coloured SfM points land on pixels of their own colour (clearly better, or an error asking to choose).
A model written with camera-to-world rotations where COLMAP expects world-to-camera ones is detected and
named ("transposes"): an earlier copy of IUI3-RedSea had such an images.bin, and only the LLFF poses fit its
images (docs/datasets.md has the measurements; the current copy's two sources agree).
"""

from __future__ import annotations

import json
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Literal

import numpy as np
import pycolmap
import torch

from uw3dgs.data.colmap_dataset import (
    ColmapModel,
    DatasetError,
    range_bounds,
    read_colmap_model,
    scene_from_model,
    z_bounds_from_points,
)
from uw3dgs.data.scene import GroundTruth, SceneData
from uw3dgs.utils.console import warn
from uw3dgs.utils.images import image_size, read_image

IMAGE_DIRS = ("Images_wb", "images_wb")
IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg")
PoseSource = Literal["auto", "colmap", "llff"]
ROTATION_TOLERANCE_DEG = 0.5
"""Pose sources agree when every view's rotations differ by less than this ..."""
CENTER_TOLERANCE = 0.01
"""... and its camera centres by less than this share of the cameras' spread."""
CLEARLY_BETTER = 0.1
"""'auto' picks the pose source whose point colour error is this much (relatively) lower than the other's."""


def find_image_dir(root: Path) -> Path:
    """`Images_wb/` as the dataset ships it, or `images_wb/`."""
    for name in IMAGE_DIRS:
        if (root / name).is_dir():
            return root / name
    raise FileNotFoundError(
        f"{root}: no image folder ({' or '.join(IMAGE_DIRS)}); point --data at a SeaThru-NeRF scene "
        "folder, or write one with `uw-synth --out DIR`"
    )


# ----------------------------------------------------------------------------------------------------
# LLFF poses_bounds.npy


@dataclass
class LlffPoses:
    """The rows of poses_bounds.npy, converted to uw3dgs' (OpenCV) conventions."""

    path: Path
    viewmats: np.ndarray
    """[N, 4, 4] world-to-camera, OpenCV axes (x right, y down, z forward)."""
    hwf: np.ndarray
    """[N, 3] image height, width and focal length in pixels, as LLFF stored them."""
    z_bounds: np.ndarray
    """[N, 2] near and far camera z-depth of each view's content."""


def read_poses_bounds(path: Path, num_images: int, images_source: str) -> LlffPoses:
    """LLFF rows [N, 17]: the 3x5 camera-to-world [R | t | (h, w, f)] with R's columns in LLFF axis order
    (down, right, back), flattened row-major, then near and far. Row k belongs to the k-th image by name."""
    try:
        rows = np.load(path)
    except (OSError, ValueError) as err:
        raise DatasetError(f"{path}: unreadable ({err}); restore the file or delete it to use sparse/0 only") \
            from err
    if rows.ndim != 2 or rows.shape[1] != 17:
        raise DatasetError(f"{path}: expected LLFF rows of 17 numbers, got shape {rows.shape}; restore the file "
                           "or delete it to use sparse/0 only")
    if len(rows) != num_images:
        raise DatasetError(
            f"{path}: {len(rows)} pose rows for {num_images} images ({images_source}); pose/image count mismatch: "
            "poses_bounds.npy needs one row per image, in file-name order. Remove the images that have no "
            "pose, or regenerate poses_bounds.npy (LLFF's imgs2poses.py)"
        )
    finite = np.isfinite(rows).all(axis=1)
    if not finite.all():
        bad = np.flatnonzero(~finite)
        rows_text = f"row {bad[0]}" + (f" (and {len(bad) - 1} more)" if len(bad) > 1 else "")
        raise DatasetError(f"{path}: {rows_text} (counted from 0: image number {bad[0] + 1} by file name) holds "
                           "NaN or infinite numbers; restore the file, regenerate it (LLFF's imgs2poses.py), or "
                           "delete it to use sparse/0 only")
    mats = rows[:, :15].reshape(-1, 3, 5)
    viewmats = np.tile(np.eye(4), (len(rows), 1, 1))
    for k, m in enumerate(mats):
        rotation = np.column_stack([m[:, 1], m[:, 0], -m[:, 2]])  # (down, right, back) -> (right, down, forward)
        viewmats[k, :3, :3] = rotation.T
        viewmats[k, :3, 3] = -rotation.T @ m[:, 3]
    return LlffPoses(path, viewmats, mats[:, :, 4].copy(), rows[:, 15:17].copy())


def list_image_files(image_dir: Path) -> list[str]:
    return sorted(p.name for p in image_dir.iterdir() if p.is_file() and p.suffix.lower() in IMAGE_SUFFIXES)


def llff_model(image_dir: Path, llff: LlffPoses, names: list[str]) -> ColmapModel:
    """A pinhole 'model' from LLFF alone: focal from hwf (rescaled if the images are not h x w), principal
    point at the image centre (LLFF's assumption), no SfM points."""
    first = image_dir / names[0]
    width, height = image_size(first)
    h, w, f = llff.hwf[0]
    if abs(width / height - w / h) > 0.01:
        raise DatasetError(f"{llff.path}: poses are for {w:.0f}x{h:.0f} images but {first} is {width}x{height} "
                           "(another aspect ratio); the images do not belong to these poses")
    f = f * width / w
    camera = pycolmap.Camera(model="PINHOLE", width=width, height=height, camera_id=1,
                             params=[f, f, width / 2, height / 2])
    return ColmapModel(names=names, cameras=[camera] * len(names), viewmats=llff.viewmats,
                       points=np.zeros((0, 3)), colors=np.zeros((0, 3), dtype=np.uint8),
                       cameras_file=llff.path, images_file=llff.path)


# ----------------------------------------------------------------------------------------------------
# Comparing pose sources


@dataclass
class PoseComparison:
    rotation_deg: np.ndarray
    """[N] angle between each view's two rotations."""
    center_offset: np.ndarray
    """[N] distance between each view's two camera centres, as a share of the cameras' spread."""
    transposed: bool
    """The first source's rotations are the transposes of the second's."""

    @property
    def agree(self) -> bool:
        return bool((self.rotation_deg < ROTATION_TOLERANCE_DEG).all()
                    and (self.center_offset < CENTER_TOLERANCE).all())

    def describe(self, a: str, b: str) -> str:
        text = (f"the poses of {a} and {b} disagree: rotations differ by up to {self.rotation_deg.max():.1f} deg "
                f"(tolerance {ROTATION_TOLERANCE_DEG}), camera centres by up to "
                f"{100 * self.center_offset.max():.1f}% of the camera spread (tolerance {100 * CENTER_TOLERANCE:.0f}%)")
        if self.transposed:
            text += f"; {a} holds the transposes of the rotations of {b} (a model written with camera-to-world " \
                    "rotations where COLMAP expects world-to-camera ones)"
        return text


def _angles_deg(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    cos = (np.einsum("nij,nij->n", a, b) - 1.0) / 2.0  # trace(a^T b)
    return np.degrees(np.arccos(np.clip(cos, -1.0, 1.0)))


def _centers(viewmats: np.ndarray) -> np.ndarray:
    return -np.einsum("nji,nj->ni", viewmats[:, :3, :3], viewmats[:, :3, 3])


def compare_poses(a: np.ndarray, b: np.ndarray) -> PoseComparison:
    """Compare two sets of world-to-camera matrices [N, 4, 4] view by view."""
    ca, cb = _centers(a), _centers(b)
    spread = max(float(np.linalg.norm(ca - ca.mean(axis=0), axis=1).max()), 1e-9)
    transposed = bool((_angles_deg(a[:, :3, :3], b[:, :3, :3].transpose(0, 2, 1)) < ROTATION_TOLERANCE_DEG).all())
    return PoseComparison(_angles_deg(a[:, :3, :3], b[:, :3, :3]), np.linalg.norm(ca - cb, axis=1) / spread,
                          transposed)


def point_color_errors(scene: SceneData, viewmats: np.ndarray | None = None) -> np.ndarray:
    """Per view, the mean absolute difference (0..255, over RGB) between each SfM point's colour and the
    pixel it projects to, under `viewmats` (default: the scene's own poses); NaN for a view that sees no
    point. A pose that fits its image scores far below the chance level (points and pixels shuffled)."""
    points = scene.points.double().numpy()
    colors = scene.point_colors.double().numpy() * 255.0
    errors = np.full(len(scene.cameras), np.nan)
    for k, camera in enumerate(scene.cameras):
        viewmat = camera.viewmat.double().numpy() if viewmats is None else viewmats[k]
        local = points @ viewmat[:3, :3].T + viewmat[:3, 3]
        front = local[:, 2] > 1e-9
        uv = local[front] @ camera.K.double().numpy().T
        uv = uv[:, :2] / uv[:, 2:]
        inside = (uv[:, 0] >= 0) & (uv[:, 0] < camera.width) & (uv[:, 1] >= 0) & (uv[:, 1] < camera.height)
        if inside.sum() < 10:
            continue
        rows, cols = torch.from_numpy(uv[inside, 1].astype(int)), torch.from_numpy(uv[inside, 0].astype(int))
        pixels = scene.images[k][rows, cols].double().numpy() * 255.0
        errors[k] = np.abs(pixels - colors[front][inside]).mean()
    return errors


def _with_poses(scene: SceneData, viewmats: np.ndarray, z_bounds: np.ndarray) -> SceneData:
    cameras = [replace(cam, viewmat=torch.tensor(vm, dtype=torch.float32)) for cam, vm in zip(scene.cameras,
                                                                                                 viewmats, strict=True)]
    intrinsics = np.stack([c.K.double().numpy() for c in cameras])
    near, far = range_bounds(z_bounds, intrinsics, [(c.width, c.height) for c in cameras])
    return replace(scene, cameras=cameras, near=near, far=far)


def choose_poses(scene: SceneData, model: ColmapModel, llff: LlffPoses, poses: PoseSource) -> SceneData:
    """`scene` was loaded with the COLMAP poses; switch to the LLFF ones if `poses` (or 'auto') says so."""
    comparison = compare_poses(model.viewmats, llff.viewmats)
    if comparison.agree:
        return scene if poses != "llff" else _with_poses(scene, llff.viewmats, llff.z_bounds)
    root = llff.path.parent
    colmap_name = model.images_file.relative_to(root) if model.images_file.is_relative_to(root) else model.images_file
    disagreement = f"{root}: " + comparison.describe(str(colmap_name), llff.path.name)
    points_z = z_bounds_from_points(model.points, model.viewmats, np.stack([c.K.double().numpy()
                                    for c in scene.cameras]), [(c.width, c.height) for c in scene.cameras])
    if poses == "llff":
        warn(f"{disagreement}; using {llff.path.name} (--datamanager.poses llff)")
        return _with_poses(scene, llff.viewmats, llff.z_bounds)
    if poses == "colmap":
        warn(f"{disagreement}; using {colmap_name} (--datamanager.poses colmap), near/far from its points")
        return _with_poses(scene, model.viewmats, points_z)
    colmap_err, llff_err = point_color_errors(scene, model.viewmats), point_color_errors(scene, llff.viewmats)
    seen = ~(np.isnan(colmap_err) | np.isnan(llff_err))
    if seen.sum() == 0:
        raise DatasetError(f"{disagreement}. No SfM point is seen under both, so uw3dgs cannot tell which is "
                           "right: choose with --datamanager.poses colmap or --datamanager.poses llff")
    c, lf = float(colmap_err[seen].mean()), float(llff_err[seen].mean())
    llff_wins = int((llff_err[seen] < colmap_err[seen]).sum())
    score = (f"mean point colour error {lf:.1f}/255 with {llff.path.name} vs {c:.1f}/255 with "
             f"{model.images_file.name}; {llff.path.name} better in {llff_wins}/{seen.sum()} views")
    if lf < (1 - CLEARLY_BETTER) * c and llff_wins >= 2 * seen.sum() / 3:
        warn(f"{disagreement}. Using {llff.path.name} ({score}); --datamanager.poses colmap overrides")
        return _with_poses(scene, llff.viewmats, llff.z_bounds)
    if c < (1 - CLEARLY_BETTER) * lf and llff_wins <= seen.sum() / 3:
        warn(f"{disagreement}. Using {colmap_name} ({score}); --datamanager.poses llff overrides")
        return _with_poses(scene, model.viewmats, points_z)
    raise DatasetError(f"{disagreement}, and neither fits the images clearly better ({score}): choose with "
                       "--datamanager.poses colmap or --datamanager.poses llff, or fix the files")


# ----------------------------------------------------------------------------------------------------
# Scenes


def read_seathru_scene(root: Path, poses: PoseSource = "auto", cache_dir: Path | None = None,
                       downscale_factor: int = 1, undistort: bool = True) -> SceneData:
    """A SeaThru-NeRF scene folder as one SceneData in dataset units (undistorted, downscaled, cached);
    the synthetic ground truth in gt/ is not read here (see `read_seathru_layout`)."""
    root = Path(root)
    if not root.is_dir():
        raise FileNotFoundError(f"{root}: no such folder; point --data at a SeaThru-NeRF scene folder")
    image_dir = find_image_dir(root)
    sparse_dir, llff_path = root / "sparse" / "0", root / "poses_bounds.npy"
    if poses == "colmap" and not sparse_dir.is_dir():
        raise FileNotFoundError(f"{sparse_dir}: no COLMAP model, but --datamanager.poses colmap asks for it; "
                                "use --datamanager.poses auto or llff")
    if poses == "llff" and not llff_path.is_file():
        raise FileNotFoundError(f"{llff_path}: missing, but --datamanager.poses llff asks for it; "
                                "use --datamanager.poses auto or colmap")
    if not sparse_dir.is_dir() and not llff_path.is_file():
        raise FileNotFoundError(f"{root}: no poses: neither a COLMAP model in sparse/0 nor poses_bounds.npy; "
                                "run structure from motion on the images first (COLMAP, or `uw-process-data`)")
    if not sparse_dir.is_dir():
        names = list_image_files(image_dir)
        llff = read_poses_bounds(llff_path, len(names), f"image files in {image_dir}")
        if len(names) < 2:
            raise DatasetError(f"{image_dir}: {len(names)} image(s); a scene needs at least 2")
        model = llff_model(image_dir, llff, names)
        return scene_from_model(model, root.name, image_dir, cache_dir, downscale_factor, z_bounds=llff.z_bounds,
                                undistort=undistort, missing_hint="poses_bounds.npy has a row for it")
    model = read_colmap_model(sparse_dir)
    llff = None
    if llff_path.is_file():
        llff = read_poses_bounds(llff_path, len(model.names), f"registered images in {model.images_file}")
    scene = scene_from_model(model, root.name, image_dir, cache_dir, downscale_factor,
                             z_bounds=None if llff is None else llff.z_bounds, undistort=undistort)
    return scene if llff is None else choose_poses(scene, model, llff, poses)


def read_ground_truth(gt_dir: Path, names: list[str]) -> GroundTruth:
    """Clean images gt/clean/<name>, ranges gt/range/<stem>.npy and gt/medium.json of a synthetic scene."""
    hint = "gt/ must hold one clean image and one range map per image; regenerate the scene with uw-synth"
    clean = []
    for name in names:
        path = gt_dir / "clean" / name
        if not path.is_file():
            raise FileNotFoundError(f"{path}: clean image missing; {hint}")
        clean.append(read_image(path))
    clean_images = torch.stack(clean)
    ranges = []
    for name in names:
        path = gt_dir / "range" / Path(name).with_suffix(".npy")
        if not path.is_file():
            raise FileNotFoundError(f"{path}: range map missing; {hint}")
        r = np.load(path).astype(np.float32)
        if r.shape != tuple(clean_images.shape[1:3]):
            raise DatasetError(f"{path}: shape {r.shape} but the images are {tuple(clean_images.shape[1:3])}; {hint}")
        ranges.append(r)
    medium_path = gt_dir / "medium.json"
    if not medium_path.is_file():
        raise FileNotFoundError(f"{medium_path}: medium parameters missing; {hint}")
    medium = json.loads(medium_path.read_text())
    return GroundTruth(clean_images, torch.from_numpy(np.stack(ranges)), medium)


def read_seathru_layout(root: Path) -> SceneData:
    """A pinhole scene in the SeaThru-NeRF layout at full resolution, with gt/ when present (the reader of
    synthetic scenes). Distorted cameras are refused: ground-truth maps are on the original pixel grid. The
    COLMAP model is required: its points (with their set noise and outliers) are part of the experiment."""
    root = Path(root)
    sparse_dir = root / "sparse" / "0"
    if root.is_dir() and not sparse_dir.is_dir():
        raise FileNotFoundError(f"{sparse_dir}: no COLMAP model; uw-synth always writes one: regenerate the scene "
                                "with `uw-synth --out DIR` (or read real data with the seathru-nerf datamanager)")
    scene = read_seathru_scene(root, undistort=False)
    gt_dir = root / "gt"
    if gt_dir.is_dir():
        scene.gt = read_ground_truth(gt_dir, scene.image_names)
    return scene
