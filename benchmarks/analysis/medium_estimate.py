"""The point-based medium estimate alone (no training) on versions of the built-in synthetic scene.

    python benchmarks/analysis/medium_estimate.py [--residual] [--report]

For the scene without open water or dark surfaces (version 1: tilt 35, no patches), the same scene
looking up at open water, and version 2 (open water and dark patches, the default), the estimate is run
with B_inf read off the open water (where the empty cells hold enough pixels) and with B_inf fitted, and
printed beside the true medium. Scenes are generated into the cache on first use (about a minute each).
`--residual` fits with Sea-thru's residual term (`--model.medium.estimate-residual`); `--report` prints the
identifiability report (fields/medium_identifiability.py) under each row.
"""

from __future__ import annotations

import argparse
import time

from torch import Tensor

from uw3dgs.datamanagers.synthetic import SyntheticDataManagerConfig
from uw3dgs.datamanagers.synthetic.config import SyntheticSceneConfig
from uw3dgs.fields.medium import MediumGridConfig
from uw3dgs.fields.medium_estimate import estimate_medium, open_water_color
from uw3dgs.fields.medium_identifiability import assess_medium

SCENES = {"version 1 (tilt 35, no patches)": (35.0, 0), "tilt 55, no patches": (55.0, 0),
          "version 2 (tilt 55, dark patches)": (55.0, 60)}


def triple(values: Tensor | tuple[float, ...]) -> str:
    return "(" + ", ".join(f"{float(x):.3f}" for x in values) + ")"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--residual", action="store_true", help="fit with Sea-thru's residual term")
    parser.add_argument("--report", action="store_true", help="print the identifiability report under each row")
    args = parser.parse_args()
    knobs = MediumGridConfig()
    print("| scene | B_inf | beta_D | beta_B | B_inf used | seconds |")
    print("|---|---|---|---|---|---:|")
    for name, (tilt, patches) in SCENES.items():
        config = SyntheticDataManagerConfig(scene=SyntheticSceneConfig(tilt_deg=tilt, num_dark_patches=patches))
        datamanager = config.setup(data=None)
        scene = datamanager.scene
        cameras = [scene.cameras[i] for i in datamanager.train_indices]
        images = [scene.images[i] for i in datamanager.train_indices]
        water = open_water_color(scene.points, cameras, images, knobs.open_water_cells, knobs.open_water_min_share,
                                 knobs.open_water_max_std, knobs.open_water_min_uniform)
        for b_inf in ([water] if water is not None else []) + [None]:
            start = time.perf_counter()
            est = estimate_medium(scene.points, scene.point_colors, cameras, images, scene.dataset_scale,
                                  b_inf=b_inf, dark_bins=knobs.dark_bins, dark_share=knobs.dark_share,
                                  sfm_cameras=scene.cameras, residual=args.residual)
            source = "fitted" if b_inf is None else "read off open water"
            print(f"| {name} | {source} | {triple(est.beta_d)} | {triple(est.beta_b)} | {triple(est.b_inf)} | "
                  f"{time.perf_counter() - start:.1f} |")
            if args.report:
                report = assess_medium(*est.observations, est.fit, b_inf, knobs.dark_bins, knobs.dark_share,
                                       args.residual)
                print("\n".join(f"|   | {line} | | | | |" for line in report.lines()))
        truth = scene.gt.medium
        print(f"| {name} | truth | {triple(truth['beta_D'])} | {triple(truth['beta_B'])} | "
              f"{triple(truth['B_inf'])} | |")


if __name__ == "__main__":
    main()
