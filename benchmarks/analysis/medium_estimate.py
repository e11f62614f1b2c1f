"""The point-based medium estimate alone (no training) on versions of the built-in synthetic scene.

    python benchmarks/analysis/medium_estimate.py [--residual] [--report]
    python benchmarks/analysis/medium_estimate.py --survey [--variants NAME ...]

For the scene without open water or dark surfaces (version 1: tilt 35, no patches), the same scene
looking up at open water, and version 2 (open water and dark patches, the default), the estimate is run
with B_inf read off the open water (where the empty cells hold enough pixels) and with B_inf fitted, and
printed beside the true medium. Scenes are generated into the cache on first use (about a minute each).
`--residual` fits with Sea-thru's residual term (`--model.medium.estimate-residual`); `--report` prints the
identifiability report (fields/medium_identifiability.py) under each row.

`--survey` compares, on the survey variants (SURVEYS: passes over the same seabed at several altitudes, with and
without open water, darkest surfaces at 3%, 10% or textured; a medium that varies across the scene; the forward
pass for reference), the single-image estimate (`--model.medium.init estimate`), the multi-view one
(fields/medium_multiview.py) and their combination by evidence (`--model.medium.init multiview`,
fields/medium_evidence.py) against the truth, before any training: one markdown table of errors in % (R/G/B;
beta_D and beta_B scored as fields over the seabed points, as the medium-recovery benchmark does), what each calls
not identified, and the sources of the combined estimate.
"""

from __future__ import annotations

import argparse
import time
from types import SimpleNamespace

import torch
from medium_recovery import SURVEYS, medium_errors  # the sibling script: its survey variants and scoring
from torch import Tensor

from uw3dgs.datamanagers.synthetic import SyntheticDataManagerConfig
from uw3dgs.datamanagers.synthetic.config import SyntheticSceneConfig
from uw3dgs.fields.medium import MediumGridConfig
from uw3dgs.fields.medium_estimate import estimate_from_views, estimate_medium, open_water_color
from uw3dgs.fields.medium_evidence import FAR_END, NOT_IDENTIFIED, VARYING, combine_by_evidence
from uw3dgs.fields.medium_identifiability import assess_medium
from uw3dgs.fields.medium_multiview import observe_and_estimate

SCENES = {"version 1 (tilt 35, no patches)": (35.0, 0), "tilt 55, no patches": (55.0, 0),
          "version 2 (tilt 55, dark patches)": (55.0, 60)}


def errors_text(errors: dict[str, list[float]]) -> str:
    return " ; ".join("/".join(f"{100 * x:.0f}" for x in errors[k]) for k in ("beta_D", "beta_B", "B_inf"))


def survey_row(name: str, options: dict) -> str:
    """One table row: the three estimates' errors, what each flags, the combined estimate's sources."""
    knobs = MediumGridConfig()
    scene_config = SyntheticSceneConfig(**options)
    datamanager = SyntheticDataManagerConfig(scene=scene_config).setup(data=None)
    scene, train = datamanager.scene, datamanager.train_indices
    cameras, images = [scene.cameras[i] for i in train], [scene.images[i] for i in train]
    start = time.perf_counter()
    single, water = estimate_from_views(knobs, scene, train)
    report = assess_medium(*single.observations, single.fit, water, knobs.dark_bins, knobs.dark_share, False,
                           knobs.identifiability, positions=single.positions, open_water=single.open_water)
    seconds_single = time.perf_counter() - start
    start = time.perf_counter()
    runs = []

    def fit(b_inf):
        runs.append(observe_and_estimate(scene.points, cameras, images, float(scene.dataset_scale), knobs.multiview,
                                         b_inf))
        return runs[-1]

    free = fit(None)  # the multi-view estimate on its own, B_inf fitted
    combined = combine_by_evidence(single, report, water, lambda b_inf: free if b_inf is None else fit(b_inf))
    seconds_multi = time.perf_counter() - start
    beta_d, beta_b, b_inf = combined.medium
    multi = SimpleNamespace(beta_d=free.fit.beta_d, beta_b=free.fit.beta_b, b_inf=free.fit.b_inf)
    both = SimpleNamespace(beta_d=beta_d, beta_b=beta_b, b_inf=b_inf)
    if combined.factor is not None:  # the field fit's start: each beta times the factor across the scene
        factor = combined.factor
        both = SimpleNamespace(b_inf=b_inf, betas=lambda world: tuple(
            beta * factor(world.double()).float()[:, None] for beta in (beta_d, beta_b)))
    weak_single = ", ".join(f"{c.name} {c.channel}" for c in report.checks if not c.identifiable) or "-"
    weak_multi = ", ".join(f"{c.name} {c.channel}" for c in free.checks if not c.identified) or "-"
    short = {NOT_IDENTIFIED: "NOT", VARYING: "field", FAR_END: "far"}
    sources = "; ".join(f"{n}: " + "/".join(short.get(c.source, c.source.split()[0])
                                             for c in combined.checks if c.name == n)
                        for n in ("beta_D", "beta_B", "B_inf"))
    clean = torch.stack([b["clean_image"] for b in datamanager.test_batches()])
    darkest = float(torch.quantile(clean[clean.sum(-1) > 0].mean(-1).double(), 0.01))
    return (f"| {name} | {free.span_ratio[1]:.2f} | {darkest:.3f} | "
            f"{errors_text(medium_errors(scene, scene_config, single))} | {weak_single} | "
            f"{errors_text(medium_errors(scene, scene_config, multi))} | {weak_multi} | "
            f"{errors_text(medium_errors(scene, scene_config, both))} | {sources} | "
            f"{seconds_single:.0f} / {seconds_multi:.0f} |")


def survey_table(names: list[str]) -> None:
    print("| variant | median span ratio | darkest 1% clean | single-image err % beta_D ; beta_B ; B_inf (R/G/B) "
          "| single-image not identifiable | multi-view err % | multi-view not identified | combined err % | "
          "combined: identified by (R/G/B) | seconds single / multi-view |")
    print("|---|---:|---:|---|---|---|---|---|---|---:|")
    for name in names:
        print(survey_row(name, SURVEYS[name]), flush=True)


def triple(values: Tensor | tuple[float, ...]) -> str:
    return "(" + ", ".join(f"{float(x):.3f}" for x in values) + ")"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--residual", action="store_true", help="fit with Sea-thru's residual term")
    parser.add_argument("--report", action="store_true", help="print the identifiability report under each row")
    parser.add_argument("--survey", action="store_true",
                        help="single-image, multi-view and combined estimates on the survey variants (SURVEYS)")
    parser.add_argument("--variants", nargs="+", choices=list(SURVEYS), default=list(SURVEYS),
                        help="with --survey: these variants only")
    args = parser.parse_args()
    if args.survey:
        survey_table(args.variants)
        return
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
