"""The built-in synthetic underwater scene: a procedural seabed seen through water with a known medium.

No real dataset gives the clean radiance, the true ranges and the true medium; this scene does, so URI
quality, depth error and medium recovery can be measured. It is written in the SeaThru-NeRF layout
(`Images_wb/`, `sparse/0/`, `poses_bounds.npy`) plus `gt/`, so one reader serves real and synthetic data.

World frame: metres, z up, mean seabed at z = 0. Cameras follow OpenCV/COLMAP (x right, y down,
z forward). Every depth here is a range: the distance along the pixel's ray from the camera centre.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
from rich.progress import Progress

from uw3dgs.datamanagers.synthetic.cameras import camera_poses, check_cameras, focus_area, intrinsics
from uw3dgs.datamanagers.synthetic.config import SyntheticSceneConfig
from uw3dgs.datamanagers.synthetic.marine_snow import add_marine_snow, marine_snow_particles, write_marine_snow
from uw3dgs.datamanagers.synthetic.memory import check_memory
from uw3dgs.datamanagers.synthetic.points import sample_points
from uw3dgs.datamanagers.synthetic.rendering import medium_parameters, render_view
from uw3dgs.datamanagers.synthetic.terrain import build_terrain
from uw3dgs.datamanagers.synthetic.writers import (
    llff_poses_bounds,
    write_colmap_model,
    write_medium,
    write_views,
    z_bounds,
)


def generate_scene(config: SyntheticSceneConfig, out_dir: Path, progress: bool = True) -> Path:
    """Write the scene to `out_dir` (new or empty) in the SeaThru-NeRF layout plus gt/; returns `out_dir`.

    gt/medium.json is written last: its presence marks a complete scene (useful for caches).
    """
    out_dir = Path(out_dir)
    if out_dir.exists() and not out_dir.is_dir():
        raise ValueError(f"{out_dir} is a file, not a folder; write the scene to a new or empty folder")
    if out_dir.exists() and any(out_dir.iterdir()):
        # Never mix with (or delete) what is there: stale views of another scene would corrupt this one.
        raise ValueError(f"{out_dir} is not empty; write the scene to a new or empty folder")
    check_memory(config)  # before anything is allocated
    seeds = np.random.SeedSequence(config.seed).spawn(4)  # independent streams: poses, terrain, points, snow
    pose_rng, terrain_rng, point_rng, snow_rng = (np.random.default_rng(s) for s in seeds)
    K = intrinsics(config)
    medium = medium_parameters(config)
    with Progress(disable=not progress, transient=True) as bar:
        task = bar.add_task("seabed", total=config.num_views + 2)
        c2w = camera_poses(config, pose_rng)
        terrain = build_terrain(config, focus_area(c2w), terrain_rng)
        check_cameras(terrain, c2w)
        bar.update(task, advance=1, description="ray casting")
        views = []
        for k, pose in enumerate(c2w):
            views.append(render_view(config, terrain, K, pose, medium))
            if not config.open_water and not np.isfinite(views[-1].ranges).all():
                raise ValueError(f"view {k} looks above the horizon, where no seabed is: open_water off needs every "
                                 "ray to point down; lower tilt_deg")
            bar.advance(task)
        bar.update(task, description="writing")
        xyz, rgb = sample_points(config, views, K, point_rng)  # from the snow-free images: specks never triangulate
        if config.marine_snow > 0:
            snows = [marine_snow_particles(config, terrain, K, pose, snow_rng) for pose in c2w]
            for view, snow in zip(views, snows, strict=True):
                view.underwater = add_marine_snow(config, view, snow, medium)
            (out_dir / "gt").mkdir(parents=True, exist_ok=True)
            write_marine_snow(out_dir / "gt" / "marine_snow.json", snows)
        write_views(out_dir, views)
        write_colmap_model(out_dir / "sparse" / "0", K, config, c2w, xyz, rgb)
        bounds = np.stack([z_bounds(v, k) for k, v in enumerate(views)])
        np.save(out_dir / "poses_bounds.npy", llff_poses_bounds(c2w, K, config, bounds))
        write_medium(out_dir / "gt" / "medium.json", config, medium)
        bar.advance(task)
    return out_dir
