"""The one reader of COLMAP-posed image folders (SeaThru-NeRF, generic COLMAP, uwbundle after SfM, synthetic).

    read_colmap_dataset(root, image_dir, sparse_dir, cache_dir=None, downscale_factor=1) -> SceneData

Cameras: PINHOLE and SIMPLE_PINHOLE are used as they are; SIMPLE_RADIAL, RADIAL and OPENCV are undistorted
to a PINHOLE camera first. Any other model is refused with an error naming cameras.bin and the model.

Undistortion. The undistorted camera is COLMAP's own (`pycolmap.undistort_camera` with its defaults,
`blank_pixels=0`): same focal lengths, and the largest image that holds no pixel from outside the
original frame, so there are no black borders and nothing to mask; this is what `colmap
image_undistorter` (and so 3DGS's convert.py) produces, which keeps results comparable with published
ones. For the real SeaThru-NeRF camera (barrel-dominated OPENCV) 1370x913 becomes 1383x917. Pixels
are resampled bilinearly (torch `grid_sample`) through a map computed once per camera with pycolmap's
own projection functions: target pixel centre -> pinhole ray (`cam_from_img`) -> distorted pixel
(`img_from_cam`), both in COLMAP's convention (pixel centre at +0.5, as uw3dgs' Camera uses).
When several cameras undistort to slightly different sizes, every view is centre-cropped to the
smallest (principal points follow), since a scene holds all views at one size.

Downscaling (integer factor f) happens here, after undistortion, one image at a time as it is read, with
the one rule of `uw3dgs.data.downscale` (area average of f x f blocks, K[:2] / f): a capture of 4K frames
never sits in memory at full resolution, and the cache holds the small images. Any processed image
(undistorted or downscaled) is written once as an 8-bit PNG to the cache (atomically), keyed by the source
file (path, size, mtime), both cameras, the factor and `READER_VERSION`, and read from there on later loads:

    <cache_dir>/colmap/<dataset folder name>-<hash of its path>/x<f>/<image name>.<key>.png

cache_dir defaults to $UW3DGS_CACHE or ~/.cache/uw3dgs (`uw3dgs.data.cache.default_cache_dir`); the
dataset folder is never written to (datasets are often read-only or shared).

Views are sorted by image name (the LLFF/SeaThru-NeRF split relies on it). Every problem with the
input raises FileNotFoundError or `DatasetError` (a ValueError) whose message names the file and the fix.
"""

from __future__ import annotations

import hashlib
import json
from collections.abc import Sequence
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np
import pycolmap
import torch
import torch.nn.functional as F
from PIL import Image

from uw3dgs.cameras import Camera
from uw3dgs.data.cache import default_cache_dir
from uw3dgs.data.downscale import area_downscale, downscale_intrinsics
from uw3dgs.data.scene import GroundTruth, SceneData
from uw3dgs.utils.console import info, warn
from uw3dgs.utils.images import read_image
from uw3dgs.utils.io import atomic_file

READER_VERSION = 1
"""Bump when the undistortion or downscaling of pixels changes: it is part of every cache key."""
PINHOLE_MODELS = ("SIMPLE_PINHOLE", "PINHOLE")
DISTORTED_MODELS = ("SIMPLE_RADIAL", "RADIAL", "OPENCV")
SUPPORTED_CAMERA_MODELS = PINHOLE_MODELS + DISTORTED_MODELS
MIN_VIEWS = 2
MAX_CROP = 0.1
"""Cameras whose (undistorted) sizes differ by more than this share are refused rather than cropped."""


class DatasetError(ValueError):
    """A dataset cannot be used as it is; the message names the file and what to do."""


@dataclass
class ColmapModel:
    """What a scene needs from a reconstruction (or from LLFF poses), views sorted by image name."""

    names: list[str]
    cameras: list[pycolmap.Camera]
    """Each view's camera as calibrated (possibly distorted); views may share one object."""
    viewmats: np.ndarray
    """[N, 4, 4] world-to-camera."""
    points: np.ndarray
    """[P, 3] point positions (P may be 0)."""
    colors: np.ndarray
    """[P, 3] uint8 point colours."""
    cameras_file: Path
    """Where the cameras came from (cameras.bin, or poses_bounds.npy), for error messages."""
    images_file: Path
    """Where the image list came from (images.bin, or poses_bounds.npy), for error messages."""


def model_file(sparse_dir: Path, stem: str) -> Path:
    """cameras.bin or cameras.txt (whichever COLMAP wrote), for error messages."""
    binary, text = sparse_dir / f"{stem}.bin", sparse_dir / f"{stem}.txt"
    return text if text.exists() and not binary.exists() else binary


def read_colmap_model(sparse_dir: Path) -> ColmapModel:
    """Registered images (sorted by name) with poses and cameras, and the 3D points with colours."""
    sparse_dir = Path(sparse_dir)
    if not sparse_dir.is_dir():
        raise FileNotFoundError(
            f"{sparse_dir}: no COLMAP model; run structure from motion on the images (COLMAP, or "
            "`uw-process-data`) and put the model (cameras, images, points3D .bin or .txt) there"
        )
    try:
        rec = pycolmap.Reconstruction(str(sparse_dir))
    except Exception as err:  # pycolmap raises bare RuntimeErrors on missing or corrupt files
        raise DatasetError(f"{sparse_dir}: cannot read the COLMAP model ({err}); it needs cameras, images and "
                           "points3D (.bin or .txt) as COLMAP writes them: re-export the model") from err
    images = sorted((im for im in rec.images.values() if im.has_pose), key=lambda im: im.name)
    if len(images) < MIN_VIEWS:
        raise DatasetError(
            f"{model_file(sparse_dir, 'images')}: {len(images)} registered image(s) with a pose; a scene needs at "
            f"least {MIN_VIEWS}. Structure from motion failed or the model is empty: re-run it with more overlap "
            "between the images"
        )
    viewmats = np.tile(np.eye(4), (len(images), 1, 1))
    for k, image in enumerate(images):
        viewmats[k, :3] = image.cam_from_world().matrix()
    point_ids = sorted(rec.points3D)
    return ColmapModel(
        names=[im.name for im in images],
        cameras=[rec.cameras[im.camera_id] for im in images],
        viewmats=viewmats,
        points=np.array([rec.points3D[i].xyz for i in point_ids], dtype=np.float64).reshape(-1, 3),
        colors=np.array([rec.points3D[i].color for i in point_ids], dtype=np.uint8).reshape(-1, 3),
        cameras_file=model_file(sparse_dir, "cameras"),
        images_file=model_file(sparse_dir, "images"),
    )


# ----------------------------------------------------------------------------------------------------
# Undistortion


def check_camera_model(camera: pycolmap.Camera, cameras_file: Path, undistort: bool = True) -> None:
    """Refuse models this reader cannot turn into a pinhole camera (or any distortion if undistort=False)."""
    supported = SUPPORTED_CAMERA_MODELS if undistort else PINHOLE_MODELS
    if camera.model_name in supported:
        return
    if not undistort and camera.model_name in DISTORTED_MODELS:
        raise DatasetError(
            f"{cameras_file}: camera {camera.camera_id} has model {camera.model_name} (lens distortion); this "
            f"reader takes undistorted cameras only ({', '.join(PINHOLE_MODELS)}). Read real data with the "
            "seathru-nerf or colmap datamanager, which undistort it"
        )
    raise DatasetError(
        f"{cameras_file}: camera {camera.camera_id} has model {camera.model_name}, which uw3dgs cannot read "
        f"(supported: {', '.join(supported)}). Re-run COLMAP with --ImageReader.camera_model OPENCV, or "
        "undistort the images first (`colmap image_undistorter`) and point --data at its output"
    )


def camera_key(camera: pycolmap.Camera) -> tuple:
    return camera.model_name, int(camera.width), int(camera.height), tuple(float(p) for p in camera.params)


def pinhole_camera(camera: pycolmap.Camera) -> pycolmap.Camera:
    """The PINHOLE camera a view is served with: the same one for pinhole models; for distorted models,
    COLMAP's undistorted camera (same focal lengths, largest image without blank pixels)."""
    if camera.model_name in PINHOLE_MODELS:
        K = camera.calibration_matrix()
        return pycolmap.Camera(model="PINHOLE", width=camera.width, height=camera.height,
                               params=[K[0, 0], K[1, 1], K[0, 2], K[1, 2]])
    undistorted = pycolmap.undistort_camera(pycolmap.UndistortCameraOptions(), camera)
    return pycolmap.Camera(model="PINHOLE", width=undistorted.width, height=undistorted.height,
                           params=list(undistorted.params))


def crop_camera(camera: pycolmap.Camera, width: int, height: int) -> pycolmap.Camera:
    """A PINHOLE camera centre-cropped to width x height (the principal point moves with the crop)."""
    fx, fy, cx, cy = camera.params
    x0, y0 = (camera.width - width) // 2, (camera.height - height) // 2
    return pycolmap.Camera(model="PINHOLE", width=width, height=height, params=[fx, fy, cx - x0, cy - y0])


def undistortion_map(source: pycolmap.Camera, target: pycolmap.Camera) -> np.ndarray:
    """[H, W, 2] position (x, y) in the `source` image of each `target` pixel centre, in COLMAP's
    continuous pixel coordinates (the centre of pixel (0, 0) is (0.5, 0.5))."""
    v, u = np.meshgrid(np.arange(target.height) + 0.5, np.arange(target.width) + 0.5, indexing="ij")
    xy = target.cam_from_img(np.stack([u.ravel(), v.ravel()], axis=-1))
    src = source.img_from_cam(np.column_stack([xy, np.ones(len(xy))]), check_cheirality=False)
    return src.reshape(target.height, target.width, 2)


def remap(image: torch.Tensor, source_xy: np.ndarray) -> torch.Tensor:
    """Bilinear resampling of `image` [H, W, C] at `source_xy` [H', W', 2] (COLMAP pixel coordinates);
    positions outside the image take the nearest border pixel (COLMAP's no-blank-pixel crop has none)."""
    h, w = image.shape[:2]
    # align_corners=False: -1 and +1 are the outer edges of the border pixels, i.e. COLMAP's 0 and w
    grid = np.stack([2.0 * source_xy[..., 0] / w - 1.0, 2.0 * source_xy[..., 1] / h - 1.0], axis=-1)
    out = F.grid_sample(image.permute(2, 0, 1)[None], torch.from_numpy(grid).to(image.dtype)[None],
                        mode="bilinear", padding_mode="border", align_corners=False)
    return out[0].permute(1, 2, 0).contiguous()


@dataclass
class ViewPlan:
    """How one view's pixels are made: source camera -> served pinhole camera (before downscaling)."""

    source: pycolmap.Camera
    target: pycolmap.Camera

    @property
    def is_identity(self) -> bool:
        return self.source.model_name in PINHOLE_MODELS and (self.source.width, self.source.height) == (
            self.target.width, self.target.height)


def plan_views(cameras: Sequence[pycolmap.Camera], cameras_file: Path, undistort: bool = True) -> list[ViewPlan]:
    """One pinhole camera per view, all of one size (centre-cropped to the smallest)."""
    pinholes: dict[tuple, pycolmap.Camera] = {}
    for camera in cameras:
        key = camera_key(camera)
        if key not in pinholes:
            check_camera_model(camera, cameras_file, undistort)
            pinholes[key] = pinhole_camera(camera)
    width = min(c.width for c in pinholes.values())
    height = min(c.height for c in pinholes.values())
    for key, cam in pinholes.items():
        if cam.width > width * (1 + MAX_CROP) or cam.height > height * (1 + MAX_CROP):
            raise DatasetError(
                f"{cameras_file}: cameras of different sizes ({cam.width}x{cam.height} for a {key[0]} camera, "
                f"the smallest is {width}x{height}); uw3dgs holds all views at one size: resize the images "
                "to one size and recalibrate"
            )
        pinholes[key] = crop_camera(cam, width, height)
    return [ViewPlan(camera, pinholes[camera_key(camera)]) for camera in cameras]


# ----------------------------------------------------------------------------------------------------
# Loading images, with the on-disk cache


class ImageCache:
    """Processed (undistorted and/or downscaled) images of one dataset as 8-bit PNGs."""

    def __init__(self, folder: Path):
        self.folder = folder
        self.hits = 0
        self.writes = 0
        self.broken: str | None = None

    @classmethod
    def for_dataset(cls, cache_dir: Path | None, image_dir: Path, factor: int) -> ImageCache:
        image_dir = Path(image_dir).resolve()
        tag = hashlib.sha256(str(image_dir).encode()).hexdigest()[:8]
        name = image_dir.parent.name if image_dir.name.lower() in ("images", "images_wb") else image_dir.name
        return cls((cache_dir or default_cache_dir()) / "colmap" / f"{name}-{tag}" / f"x{factor}")

    def path(self, name: str, key: str) -> Path:
        rel = Path(name)
        return self.folder / rel.parent / f"{rel.stem}.{key}.png"

    def read(self, path: Path) -> torch.Tensor | None:
        if not path.is_file():
            return None
        try:
            image = read_image(path)
        except ValueError:  # a damaged cache entry is rebuilt, never an error
            return None
        self.hits += 1
        return image

    def write(self, path: Path, pixels: np.ndarray) -> None:
        if self.broken is not None:
            return
        try:
            with atomic_file(path, "wb") as f:  # a killed run leaves no half-written entry
                # fast zlib level: much quicker to write than the default for slightly larger files (docs/datasets.md)
                Image.fromarray(pixels).save(f, format="PNG", compress_level=1)
            self.writes += 1
        except OSError as err:
            self.broken = f"{self.folder}: cannot write the image cache ({err}); images are processed on every " \
                          "load. Set $UW3DGS_CACHE (or --datamanager.cache-dir) to a writable folder"
            warn(self.broken)


def view_cache_key(path: Path, plan: ViewPlan, factor: int) -> str:
    stat = path.stat()
    payload = {"version": READER_VERSION, "source_file": [str(path.resolve()), stat.st_size, stat.st_mtime_ns],
               "camera": camera_key(plan.source), "target": camera_key(plan.target), "factor": factor}
    return hashlib.sha256(json.dumps(payload, sort_keys=True).encode()).hexdigest()[:12]


def process_view(image: torch.Tensor, plan: ViewPlan, factor: int,
                 maps: dict[tuple, np.ndarray] | None = None) -> torch.Tensor:
    """Undistort (or crop) one full-resolution image [H, W, 3] to its plan's pinhole camera, then downscale.
    `maps` keeps the undistortion map of each camera between the views of one load."""
    if plan.source.model_name in PINHOLE_MODELS:
        x0 = (plan.source.width - plan.target.width) // 2
        y0 = (plan.source.height - plan.target.height) // 2
        image = image[y0:y0 + plan.target.height, x0:x0 + plan.target.width]
    else:
        maps = {} if maps is None else maps
        key = (camera_key(plan.source), camera_key(plan.target))
        if key not in maps:
            maps[key] = undistortion_map(plan.source, plan.target)
        image = remap(image, maps[key])
    return area_downscale(image, factor)


def load_view(image_dir: Path, name: str, plan: ViewPlan, factor: int, cache: ImageCache | None,
              missing_hint: str, cameras_file: Path, maps: dict[tuple, np.ndarray] | None = None) -> torch.Tensor:
    """One view as float32 [H, W, 3] in [0, 1], undistorted and downscaled (from the cache when there)."""
    path = image_dir / name
    if not path.is_file():
        raise FileNotFoundError(f"{path}: image missing; {missing_hint}")
    processed = not (plan.is_identity and factor == 1)
    entry = cache.path(name, view_cache_key(path, plan, factor)) if processed and cache is not None else None
    if entry is not None and cache is not None:
        image = cache.read(entry)
        if image is not None:
            return image
    image = read_image(path)  # ImageReadError (a ValueError) names the file when it is truncated or corrupt
    height, width = image.shape[:2]
    if (width, height) != (plan.source.width, plan.source.height):
        raise DatasetError(
            f"{path}: {width}x{height} pixels but its camera {plan.source.camera_id} in {cameras_file} is "
            f"{plan.source.width}x{plan.source.height} (mixed image sizes for one camera); images and model "
            "must match: restore the original image or recalibrate"
        )
    if not processed:
        return image
    pixels = np.rint(process_view(image, plan, factor, maps).clamp(0, 1).numpy() * 255.0).astype(np.uint8)
    if entry is not None and cache is not None:
        cache.write(entry, pixels)
    return torch.from_numpy(pixels.astype(np.float32) / 255.0)


def load_views(image_dir: Path, names: list[str], plans: list[ViewPlan], factor: int, cache: ImageCache | None,
               missing_hint: str, cameras_file: Path) -> torch.Tensor:
    """All views [N, H, W, 3] float32 in [0, 1]."""
    maps: dict[tuple, np.ndarray] = {}  # one undistortion map per camera, computed on first need
    images = [load_view(image_dir, name, plan, factor, cache, missing_hint, cameras_file, maps)
              for name, plan in zip(names, plans, strict=True)]
    if cache is not None and cache.writes:
        info(f"wrote {cache.writes} undistorted/downscaled image(s) to {cache.folder} "
             "(first use; later loads reuse them)")
    return torch.stack(images)


# ----------------------------------------------------------------------------------------------------
# Near / far bounds and initial points


def z_bounds_from_points(points: np.ndarray, viewmats: np.ndarray, intrinsics: np.ndarray,
                         sizes: list[tuple[int, int]]) -> np.ndarray:
    """Per-view (near, far) z-depths of the points each view sees, LLFF's 0.1 / 99.9 percentiles; views
    that see no point take the bounds over all views."""
    bounds = np.full((len(viewmats), 2), np.nan)
    for k, (viewmat, K, (width, height)) in enumerate(zip(viewmats, intrinsics, sizes, strict=True)):
        cam = points @ viewmat[:3, :3].T + viewmat[:3, 3]
        z = cam[:, 2]
        front = z > 1e-6
        uv = cam[front] @ K.T
        uv = uv[:, :2] / uv[:, 2:]
        inside = (uv[:, 0] >= 0) & (uv[:, 0] <= width) & (uv[:, 1] >= 0) & (uv[:, 1] <= height)
        if inside.any():
            bounds[k] = np.percentile(z[front][inside], [0.1, 99.9])
    if np.isnan(bounds).all():
        raise DatasetError("no poses_bounds.npy and no 3D point inside any view: cannot set near/far; check that "
                           "the points3D file belongs to this model")
    bounds[np.isnan(bounds[:, 0])] = [np.nanmin(bounds[:, 0]), np.nanmax(bounds[:, 1])]
    return bounds


def range_bounds(z_bounds: np.ndarray, intrinsics: np.ndarray, sizes: list[tuple[int, int]]) -> tuple[float, float]:
    """Scene near/far along the rays from per-view z-depth bounds: range >= z everywhere, and the range
    of a point at z-depth z is at most z times the ray-length factor |K^-1 (u, v, 1)| of an image corner."""
    corner_factor = 1.0
    for K, (width, height) in zip(intrinsics, sizes, strict=True):
        corners = np.array([[0, 0, 1], [width, 0, 1], [0, height, 1], [width, height, 1]], dtype=float)
        corner_factor = max(corner_factor, float(np.linalg.norm(corners @ np.linalg.inv(K).T, axis=1).max()))
    return float(z_bounds[:, 0].min()), float(z_bounds[:, 1].max()) * corner_factor


def points_from_views(images: torch.Tensor, cameras: list[Camera], z_bounds: np.ndarray, count: int = 20000,
                      seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """Initial points for a dataset without SfM points (LLFF poses only): random pixels of every view lifted
    to a random z-depth uniform in inverse depth between the view's bounds, coloured by the pixel."""
    rng = np.random.default_rng(seed)
    per_view = max(1, count // len(cameras))
    points, colors = [], []
    for image, camera, (near, far) in zip(images.numpy(), cameras, z_bounds, strict=True):
        K, viewmat = camera.K.double().numpy(), camera.viewmat.double().numpy()
        u = rng.uniform(0, camera.width, per_view)
        v = rng.uniform(0, camera.height, per_view)
        z = 1.0 / rng.uniform(1.0 / far, 1.0 / near, per_view)
        cam = np.stack([(u - K[0, 2]) / K[0, 0] * z, (v - K[1, 2]) / K[1, 1] * z, z], axis=-1)
        points.append((cam - viewmat[:3, 3]) @ viewmat[:3, :3])  # R^T (x - t) as row vectors
        colors.append(np.rint(image[v.astype(int), u.astype(int)] * 255).astype(np.uint8))
    return np.concatenate(points), np.concatenate(colors)


# ----------------------------------------------------------------------------------------------------
# Whole scenes


def scene_from_model(model: ColmapModel, name: str, image_dir: Path, cache_dir: Path | None = None,
                     downscale_factor: int = 1, *, z_bounds: np.ndarray | None = None, undistort: bool = True,
                     missing_hint: str | None = None) -> SceneData:
    """Load, undistort and downscale the images of `model` into a SceneData (dataset units, not normalised).

    downscale_factor: a positive integer (checked by the datamanager); each image is downscaled as it is read.
    z_bounds: per-view (near, far) camera z-depths (LLFF's bounds); from the points when None.
    """
    image_dir = Path(image_dir)
    if not image_dir.is_dir():
        raise FileNotFoundError(f"{image_dir}: image folder missing; point --data at the dataset folder that "
                                f"holds it (the model is {model.images_file})")
    if len(model.names) < MIN_VIEWS:
        raise DatasetError(f"{model.images_file}: {len(model.names)} posed image(s); a scene needs at least "
                           f"{MIN_VIEWS}")
    plans = plan_views(model.cameras, model.cameras_file, undistort)
    cache = ImageCache.for_dataset(cache_dir, image_dir, downscale_factor)
    hint = missing_hint or f"{model.images_file} lists it: restore the image, or remove it from the model"
    images = load_views(image_dir, model.names, plans, downscale_factor, cache, hint, model.cameras_file)
    intrinsics = np.stack([plan.target.calibration_matrix() for plan in plans])
    full_sizes = [(plan.target.width, plan.target.height) for plan in plans]
    if z_bounds is None:
        z_bounds = z_bounds_from_points(model.points, model.viewmats, intrinsics, full_sizes)
    elif len(z_bounds) != len(model.names):
        raise DatasetError(f"{len(z_bounds)} near/far bounds for {len(model.names)} images in {model.images_file}")
    near, far = range_bounds(np.asarray(z_bounds, dtype=float), intrinsics, full_sizes)
    cameras = []
    for viewmat, K, (full_width, full_height), view_name in zip(model.viewmats, intrinsics, full_sizes, model.names,
                                                                 strict=True):
        K, width, height = downscale_intrinsics(K, full_width, full_height, downscale_factor)  # in float64
        cameras.append(Camera(torch.tensor(viewmat, dtype=torch.float32), torch.tensor(K, dtype=torch.float32),
                              width, height, view_name))
    points, colors = model.points, model.colors
    if len(points) == 0:
        points, colors = points_from_views(images, cameras, np.asarray(z_bounds, dtype=float))
    return SceneData(
        name=name,
        image_names=list(model.names),
        images=images,
        cameras=cameras,
        points=torch.tensor(points, dtype=torch.float32),
        point_colors=torch.tensor(colors, dtype=torch.float32) / 255.0,
        near=near,
        far=far,
    )


def read_colmap_dataset(root: Path, image_dir: Path, sparse_dir: Path, cache_dir: Path | None = None,
                        downscale_factor: int = 1) -> SceneData:
    """A COLMAP-posed image folder as one SceneData: views sorted by name, distorted cameras undistorted to
    pinhole, images downscaled by `downscale_factor` (through the on-disk cache), SfM points, near/far
    (range along the rays) from the points. Dataset units: no normalisation (see `normalize_scene`).

    root: the dataset folder (its name names the scene); image_dir: the images, named as in the model;
    sparse_dir: the COLMAP model (cameras, images, points3D .bin or .txt); cache_dir: where processed
    images go (default $UW3DGS_CACHE or ~/.cache/uw3dgs).
    """
    return scene_from_model(read_colmap_model(Path(sparse_dir)), Path(root).name, Path(image_dir), cache_dir,
                            downscale_factor)


# ----------------------------------------------------------------------------------------------------
# Normalisation


def normalize_scene(scene: SceneData) -> SceneData:
    """Centre the scene on the mean camera centre and scale it so that the median camera-to-point distance
    of the initial points is 1 (see docs/datasets.md for why depth rather than camera spread).

    world = (dataset - center) / scale; poses, points, near/far (and ground-truth ranges) follow.
    """
    centers = np.stack([c.center.double().numpy() for c in scene.cameras])
    center = centers.mean(axis=0)
    scale = median_point_distance(scene.points.double().numpy(), scene.cameras)
    cameras = []
    for cam in scene.cameras:
        viewmat = cam.viewmat.double().clone()
        R, t = viewmat[:3, :3], viewmat[:3, 3]
        viewmat[:3, 3] = (R @ torch.from_numpy(center) + t) / scale
        cameras.append(Camera(viewmat.float(), cam.K.clone(), cam.width, cam.height, cam.name))
    points = ((scene.points.double() - torch.from_numpy(center)) / scale).float()
    gt = scene.gt
    if gt is not None:
        gt = GroundTruth(gt.clean_images, gt.ranges / scale, gt.medium)
    return replace(scene, cameras=cameras, points=points, near=scene.near / scale, far=scene.far / scale, gt=gt,
                   dataset_center=tuple(float(x) for x in center), dataset_scale=float(scale))


def median_point_distance(points: np.ndarray, cameras: list[Camera]) -> float:
    """Median over views of the median distance from the camera centre to the points in front of it."""
    per_view = []
    for cam in cameras:
        viewmat = cam.viewmat.double().numpy()
        local = points @ viewmat[:3, :3].T + viewmat[:3, 3]
        front = local[local[:, 2] > 0]
        if len(front):
            per_view.append(np.median(np.linalg.norm(front, axis=1)))
    if not per_view:
        raise DatasetError("no initial point lies in front of any camera: cannot normalise the scene; check the "
                           "poses (or turn normalisation off with --datamanager.no-normalize)")
    return float(np.median(per_view))


def denormalize_points(points: np.ndarray, scene: SceneData) -> np.ndarray:
    """World (normalised) positions back to dataset units."""
    return np.asarray(points) * scene.dataset_scale + np.asarray(scene.dataset_center)

