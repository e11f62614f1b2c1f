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
import shutil
import tempfile
import time
import uuid
from dataclasses import dataclass, replace
from pathlib import Path
from typing import ClassVar, Literal

import numpy as np
import pycolmap
import torch

from uw3dgs.data import colmap_dataset
from uw3dgs.data.cache import default_cache_dir
from uw3dgs.data.datamanager import DataManagerConfig
from uw3dgs.data.dataparser import DataParser
from uw3dgs.data.ply import read_ply_points
from uw3dgs.data.ply import write_ply_points as write_ply_points
from uw3dgs.data.scene import SceneData
from uw3dgs.data.sfm import IMAGE_EXTENSIONS, list_images, quiet_colmap, run_sfm
from uw3dgs.datamanagers.uwbundle.calib import CalibCamera as CalibCamera
from uw3dgs.datamanagers.uwbundle.calib import CalibError as CalibError
from uw3dgs.datamanagers.uwbundle.calib import StereoCalibration, read_calib
from uw3dgs.datamanagers.uwbundle.calib import write_calib as write_calib
from uw3dgs.datamanagers.uwbundle.geometry import apply_similarity as apply_similarity
from uw3dgs.datamanagers.uwbundle.geometry import distance_to_ground_truth as distance_to_ground_truth
from uw3dgs.datamanagers.uwbundle.geometry import umeyama as umeyama
from uw3dgs.registry import DataManagerSpec
from uw3dgs.utils.console import info, warn
from uw3dgs.utils.images import image_size
from uw3dgs.utils.io import atomic_folder

SFM_VERSION = 1
"""Bump when the SfM recipe changes: it is part of the cache key, so cached models are rebuilt."""
STAMP = "uw3dgs_sfm.json"
"""Written next to a model this datamanager made (ROOT/sparse/uw3dgs_sfm.json): its cache key and stats."""
SIDES = ("left", "right")


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
            info(f"{side} images are {size[0]}x{size[1]}, the calibration is for {cam.width}x{cam.height}; "
                 "intrinsics rescaled to match")
        cameras[folder] = fixed
    info(f"{root.name}: no camera poses yet; running structure from motion on {len(names)} images "
         f"({len(pairs)} stereo pairs) with the calibrated intrinsics. This happens once; the model is cached.")
    start = time.perf_counter()
    in_dataset = _writable(root) and (stamp is not None or _empty_or_missing(root / "sparse"))
    target_parent = root / "sparse" if in_dataset else cache_parent / "sparse"
    target_parent.parent.mkdir(parents=True, exist_ok=True)
    work = Path(tempfile.mkdtemp(prefix=".sfm-", dir=target_parent.parent))  # scratch: database, mapping
    try:
        sparse = run_sfm(image_root, work, cameras, matcher=matcher, progress=progress,
                         sequence_key=lambda name: str(Path(name.split("/", 1)[1]).with_suffix("")),
                         quality_check=lambda rec: stereo_badness(check_stereo(rec, pairs, calib)))
        rec = pycolmap.Reconstruction(str(sparse))
        check = check_stereo(rec, pairs, calib)
        if check.pairs:
            rec.transform(pycolmap.Sim3d(check.scale, pycolmap.Rotation3d(), np.zeros(3)))
        _warn_stereo(check, calib, target_parent / "0")
        stats = {"key": key, "registered": rec.num_reg_images(), "images": len(names), "points": rec.num_points3D(),
                 "seconds": round(time.perf_counter() - start, 1), "matcher": matcher, "stereo_pairs_used": check.pairs,
                 "scale_to_calibration_units": check.scale, "baseline_spread": check.baseline_spread,
                 "stereo_rotation_error_deg": check.rotation_error_deg, "sfm_version": SFM_VERSION}
        # Model and stamp appear together (one folder, renamed into place): a killed run never leaves a
        # stamp-less model that a later load would take for the user's own. Our own stale model (images or
        # calibration changed) is replaced; the same model written meanwhile by another process is kept.
        existing = _read_stamp(target_parent)
        stale = (existing is not None and existing.get("key") != key) or _empty_or_missing(target_parent)
        with atomic_folder(target_parent, replace=stale) as out:
            (out / "0").mkdir()
            rec.write_binary(str(out / "0"))
            (out / STAMP).write_text(json.dumps(stats, indent=2) + "\n")
        if (_read_stamp(target_parent) or {}).get("key") != key:
            raise ValueError(f"{target_parent}: a folder that uw3dgs did not write is in the way of the structure "
                             "from motion model; move it away and load the dataset again")
    finally:
        shutil.rmtree(work, ignore_errors=True)
    return target_parent / "0"


def _empty_or_missing(folder: Path) -> bool:
    """No `folder`, or an empty one (which a new model may take the place of)."""
    return not folder.exists() or (folder.is_dir() and not any(folder.iterdir()))


def _first_image_size(image_root: Path, names: list[str]) -> tuple[int, int]:
    return image_size(image_root / sorted(names)[0])


MAX_BASELINE_SPREAD = 0.1
"""A rigid rig's SfM baselines should agree within this relative spread (what good and wrong models showed:
docs/uwbundle.md, "First use")."""
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
        warn(f"no stereo pair registered with both images; the model keeps SfM's arbitrary scale instead of "
             f"{calib.path}'s units")
        return
    if stereo_badness(check)[0] > 1.0:
        warn(f"the SfM poses disagree with {calib.path} over {check.pairs} stereo pairs "
             f"(baseline spread {100 * check.baseline_spread:.0f}%, rotation off by {check.rotation_error_deg:.1f} "
             "deg): the model is probably wrong. Structure from motion may have settled in a wrong local minimum "
             "(try --datamanager.matcher sequential, or more images), left/ and right/ may be swapped, or the "
             f"calibration may be another rig's. Delete {model.parent} to run it again.")


def load_model_scene(root: Path, image_root: Path, sparse_dir: Path, cache_dir: Path | None,
                     downscale_factor: int = 1) -> SceneData:
    """read_colmap_dataset on the model (downscaled one image at a time while reading, through the image
    cache). Camera models that reader cannot undistort (FULL_OPENCV, used when the calibration has k3 != 0)
    are undistorted by COLMAP first (pycolmap.undistort_images), once, into the cache:
    <cache_dir>/uwbundle/undistorted-<hash of the model and image folder>/ (written whole, atomically)."""
    rec = pycolmap.Reconstruction(str(sparse_dir))
    if all(c.model_name in colmap_dataset.SUPPORTED_CAMERA_MODELS for c in rec.cameras.values()):
        return colmap_dataset.read_colmap_dataset(root, image_root, sparse_dir, cache_dir, downscale_factor)
    digest = hashlib.sha256(str(image_root.resolve()).encode())
    for path in sorted(sparse_dir.iterdir()):
        digest.update(path.name.encode() + path.read_bytes())
    undistorted = (cache_dir or default_cache_dir()) / "uwbundle" / f"undistorted-{digest.hexdigest()[:16]}"
    if not (undistorted / "sparse").is_dir():
        # a killed run leaves no half-undistorted folder behind; a folder without sparse/ is replaced
        with atomic_folder(undistorted, replace=True) as tmp, quiet_colmap():
            pycolmap.undistort_images(str(tmp), str(sparse_dir), str(image_root))
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
# The data plugin


class UWBundleDataParser(DataParser):
    """A UWBundle folder through `read_uwbundle`: SfM on first use, undistorted, and downscaled one image at a
    time while reading (through the image cache), normalised unless --datamanager.no-normalize."""

    config: UWBundleDataManagerConfig

    def parse(self, data: Path | None, downscale_factor: int) -> SceneData:
        if data is None:
            raise ValueError("the uwbundle datamanager needs --data: a folder with a .calib file and left/, right/ "
                             "image folders (see docs/uwbundle.md)")
        return read_uwbundle(Path(data), self.config.matcher, self.config.cache_dir, downscale_factor,
                             normalize=self.config.normalize)


@dataclass(frozen=True)
class UWBundleDataManagerConfig(DataManagerConfig):
    matcher: Literal["exhaustive", "sequential"] = "exhaustive"
    """First-use SfM matching: exhaustive (every pair, up to a few hundred images) or sequential (by file name)."""
    cache_dir: Path | None = None
    """Processed images, and SfM models of read-only datasets; default $UW3DGS_CACHE or ~/.cache/uw3dgs."""
    normalize: bool = True
    """Centre on the cameras, median point distance 1 (recorded in the run); dataset units are the .calib's."""
    parser: ClassVar[type[DataParser]] = UWBundleDataParser

    @classmethod
    def can_read(cls, path: Path) -> bool:
        """A folder holding a .calib stereo calibration file."""
        return path.is_dir() and any(p.suffix.lower() == ".calib" and p.is_file() for p in path.iterdir())


datamanager = DataManagerSpec(
    "uwbundle", "UWBundle stereo captures (.calib + left/ right/ images + groundtruth.ply); structure from motion "
    "with the calibrated intrinsics runs once on first use.", UWBundleDataManagerConfig())
