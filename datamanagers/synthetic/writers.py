"""Writing the scene in the SeaThru-NeRF layout (`Images_wb/`, `sparse/0/`, `poses_bounds.npy`) plus `gt/`."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pycolmap
from PIL import Image

from uw3dgs.datamanagers.synthetic.config import GENERATOR_VERSION, SyntheticSceneConfig, config_record
from uw3dgs.datamanagers.synthetic.rendering import RenderedView
from uw3dgs.datamanagers.synthetic.water_types import SOURCES as WATER_TYPE_SOURCES
from uw3dgs.datamanagers.synthetic.water_types import WAVELENGTHS_NM

# Writing the SeaThru-NeRF layout


def image_names(n: int) -> list[str]:
    return [f"{k:04d}.png" for k in range(n)]


def write_colmap_model(sparse_dir: Path, K: np.ndarray, cfg: SyntheticSceneConfig, c2w: np.ndarray,
                       xyz: np.ndarray, rgb: np.ndarray) -> None:
    """cameras.bin (one PINHOLE camera), images.bin (world-to-camera poses), points3D.bin (empty tracks)."""
    rec = pycolmap.Reconstruction()
    params = [K[0, 0], K[1, 1], K[0, 2], K[1, 2]]
    rec.add_camera_with_trivial_rig(
        pycolmap.Camera(model="PINHOLE", width=cfg.width, height=cfg.height, params=params, camera_id=1)
    )
    for k, name in enumerate(image_names(len(c2w))):
        w2c = np.linalg.inv(c2w[k])
        pose = pycolmap.Rigid3d(pycolmap.Rotation3d(w2c[:3, :3]), w2c[:3, 3])
        rec.add_image_with_trivial_frame(pycolmap.Image(name=name, camera_id=1, image_id=k + 1), pose)
    for p, c in zip(xyz, rgb, strict=True):
        rec.add_point3D(p, pycolmap.Track(), c)
    sparse_dir.mkdir(parents=True, exist_ok=True)
    rec.write_binary(str(sparse_dir))
    # COLMAP >= 3.12 adds rigs.bin and frames.bin; the dataset ships the classic three files only, and
    # readers (pycolmap included) rebuild trivial rigs without them.
    for extra in ("rigs.bin", "frames.bin"):
        (sparse_dir / extra).unlink(missing_ok=True)


def llff_poses_bounds(c2w: np.ndarray, K: np.ndarray, cfg: SyntheticSceneConfig,
                      z_bounds: np.ndarray) -> np.ndarray:
    """LLFF rows [N, 17]: the 3x5 matrix [R | t | (h, w, f)] of camera-to-world in LLFF axis order
    (down, right, back), flattened row-major, then the near and far z-depth bounds."""
    rows = []
    hwf = np.array([cfg.height, cfg.width, K[0, 0]], dtype=float)
    for pose, bounds in zip(c2w, z_bounds, strict=True):
        r = pose[:3, :3]
        llff = np.column_stack([r[:, 1], r[:, 0], -r[:, 2], pose[:3, 3], hwf])
        rows.append(np.concatenate([llff.ravel(), bounds]))
    return np.stack(rows)


def z_bounds(view: RenderedView, index: int) -> np.ndarray:
    """Near and far camera z-depth of the visible seabed, as LLFF stores them."""
    z = view.ranges * (view.centre_dirs @ view.c2w[:3, 2])
    z = z[np.isfinite(z)]
    if z.size == 0:
        raise ValueError(f"view {index} sees no seabed: lower tilt_deg or altitude")
    return np.array([z.min(), z.max()])


def _write_png(path: Path, pixels: np.ndarray) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    Image.fromarray(pixels).save(path)


def write_views(out_dir: Path, views: list[RenderedView]) -> None:
    for name, view in zip(image_names(len(views)), views, strict=True):
        _write_png(out_dir / "Images_wb" / name, view.underwater)
        _write_png(out_dir / "gt" / "clean" / name, view.clean)
        range_path = out_dir / "gt" / "range" / Path(name).with_suffix(".npy")
        range_path.parent.mkdir(parents=True, exist_ok=True)
        np.save(range_path, view.ranges.astype(np.float32))


def write_medium(path: Path, cfg: SyntheticSceneConfig, medium: dict[str, np.ndarray]) -> None:
    """gt/medium.json: beta_D, beta_B, B_inf (the homogeneous medium, or a varying one's reference values), units,
    seed, generator version and config; with a water type its name and sources, with a medium profile its formula
    and parameters (`beta_field` evaluates it)."""
    content = {key: [float(x) for x in value] for key, value in medium.items()}
    content |= {"units": "per metre (world unit)", "seed": cfg.seed, "generator_version": GENERATOR_VERSION,
                "config": config_record(cfg)}
    if cfg.water_type is not None:
        content["water_type"] = {"name": cfg.water_type, "wavelengths_nm": list(WAVELENGTHS_NM),
                                 "water_light": cfg.water_light, "sources": WATER_TYPE_SOURCES}
    if cfg.medium_profile != "homogeneous":
        formula = {"turbid-bottom": "1 + gain * exp(-max(z, 0) / height), z = height above the mean seabed",
                   "plume": "1 + gain * exp(-|x - center|^2 / (2 radius^2))",
                   "gradient": "1 + gain * (1 + tanh(s / length)) / 2, s = (x, y) - center along (cos a, sin a), "
                               "a = azimuth"}[cfg.medium_profile]
        profile = {"kind": cfg.medium_profile, "gain": cfg.medium_profile_gain, "factor": formula,
                   "meaning": "beta_D(x) = beta_D * factor(x) and beta_B(x) = beta_B * factor(x), with beta_D and "
                              "beta_B above the reference values (factor 1); B_inf is one colour. A pixel sees the "
                              "mean of beta along its ray from the camera to the seabed."}
        if cfg.medium_profile == "turbid-bottom":
            profile["height"] = cfg.turbid_height
        elif cfg.medium_profile == "gradient":
            profile |= {"azimuth_deg": cfg.gradient_azimuth_deg, "length": cfg.gradient_length,
                        "center": list(cfg.gradient_center)}
        else:
            profile |= {"radius": cfg.plume_radius, "center": list(cfg.plume_center)}
        content["medium_profile"] = profile
    path.write_text(json.dumps(content, indent=2, sort_keys=True) + "\n")
