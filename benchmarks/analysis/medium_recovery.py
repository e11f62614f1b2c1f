"""Medium recovery across versions of the built-in synthetic scene: estimate, trained run, verdict.

    python benchmarks/analysis/medium_recovery.py --steps 3000 --output-dir outputs/medium-recovery
    python benchmarks/analysis/medium_recovery.py --variants default 3C plume-grid plume-homogeneous
    python benchmarks/analysis/medium_recovery.py --variants survey-2-passes-no-open-water --seeds 0 1 2

For each variant (VARIANTS: water types, open water, darkest albedo, range span, a varying medium with the VM grid
and with the homogeneous field) it
1. runs the point-based medium estimate the model starts from (as `uw3dgs` does before step 1; also with Sea-thru's
   residual term, `--model.medium.estimate-residual`) and its identifiability report (fields/medium_identifiability.py);
2. trains `uw-train uw3dgs --max-num-iterations STEPS --seed 0 [method options] synthetic [scene options]` into
   OUTPUT_DIR/VARIANT/ (with `--seeds`, once per seed into OUTPUT_DIR/sSEED/VARIANT/, a row each) and evaluates
   it (`uw-eval`), unless that folder already holds the evaluation (a killed benchmark resumes: a half-trained run
   continues from its last checkpoint);
3. scores both media against the truth, per channel: B_inf against gt/medium.json, beta_D and beta_B as a field:
   the mean over the scene's seabed points (its initial points) of |beta(x) - beta_true(x)| / beta_true(x), with
   beta_true = `beta_field` (datamanagers/synthetic/scene.py), the reference medium times the profile (1 without
   one), so a spatially varying medium is scored where it varies (also kept: the same at the trained Gaussians'
   centres, and the betas averaged along each test pixel's ray against the true ray mean, what the images see);
and prints one markdown table: errors in % (R/G/B), the input's and the URI's PSNR against the clean test images,
the verdict, and whether the bar is met (identifiable parameters within 15% after training, URI at least
6 dB closer to the clean truth than the input), then the verdicts' reasons, then the URI where the water leaves
the seabed recoverable (`recoverable_psnr`: within the report's recoverable range), then for the varying media the
three field errors and how the trained field varies (its spread and its correlation with the truth at the seabed
points). Each variant's numbers are kept in OUTPUT_DIR/VARIANT/row.json. `--scene KEY=VALUE` sets a scene option
for every variant (the test: tiny images); `--train-flags` adds uw-train method options to every variant's
(diagnostics), `--grid-flags` the VM grid's options to the variants that train the grid.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import re
import shlex
import shutil
from pathlib import Path
from types import SimpleNamespace

import torch

from uw3dgs.cli.train import entrypoint as train_entrypoint
from uw3dgs.datamanagers.synthetic import SyntheticDataManagerConfig
from uw3dgs.datamanagers.synthetic.config import SyntheticSceneConfig
from uw3dgs.datamanagers.synthetic.rendering import beta_field, ray_mean_factor
from uw3dgs.engine.checkpoint import checkpoint_step, latest_checkpoint
from uw3dgs.engine.evaluator import load_trained
from uw3dgs.engine.run_folder import NOTES_DIR
from uw3dgs.fields.medium_estimate import estimate_from_views
from uw3dgs.fields.medium_evidence import NOT_IDENTIFIED
from uw3dgs.fields.medium_identifiability import assess_medium
from uw3dgs.fields.medium_varying import FactorField
from uw3dgs.metrics.image import psnr
from uw3dgs.registry import METHODS

# the VM grid as the paper's code starts it (uw3dgs-paper's): a zero basis and the factors' norm in L_beta, which
# collapses the factors (the default start keeps them alive: constant planes and lines, a roughness penalty)
ZERO_BASIS = ["--model.medium.flat-start", "zero-basis", "--model.medium.factor-penalty", "norm",
              "--model.medium.factor-penalty-weight", "0.001"]
# name -> (scene options, method options); scene options are SyntheticSceneConfig fields
VARIANTS: dict[str, tuple[dict, list[str]]] = {
    "default": ({}, []),
    "I": ({"water_type": "I"}, []),
    "II": ({"water_type": "II"}, []),
    "III": ({"water_type": "III"}, []),
    "1C": ({"water_type": "1C"}, []),
    "3C": ({"water_type": "3C"}, []),
    "5C": ({"water_type": "5C"}, []),
    "7C": ({"water_type": "7C"}, []),
    "9C": ({"water_type": "9C"}, []),
    "no-open-water": ({"open_water": False}, []),
    "albedo-0.1": ({"dark_patch_albedo": 0.1}, []),
    "albedo-0.2": ({"dark_patch_albedo": 0.2}, []),
    "narrow-range": ({"altitude": 1.5, "tilt_deg": 5.0}, []),
    "no-open-water-albedo-0.1": ({"open_water": False, "dark_patch_albedo": 0.1}, []),
    "turbid-bottom-grid": ({"medium_profile": "turbid-bottom"}, ["medium-grid"]),
    "turbid-bottom-homogeneous": ({"medium_profile": "turbid-bottom"}, ["medium-homogeneous"]),
    "plume-grid": ({"medium_profile": "plume"}, ["medium-grid"]),
    "plume-homogeneous": ({"medium_profile": "plume"}, ["medium-homogeneous"]),
    "turbid-bottom-grid-zero-basis": ({"medium_profile": "turbid-bottom"}, ["medium-grid", *ZERO_BASIS]),
    "plume-grid-zero-basis": ({"medium_profile": "plume"}, ["medium-grid", *ZERO_BASIS]),
}
# the survey variants (passes over the same seabed at one to three altitudes; also medium_estimate.py --survey):
# name -> scene options (SyntheticSceneConfig fields)
SURVEYS: dict[str, dict] = {
    "forward, open water": {},
    "forward, no open water, darkest 10%": {"open_water": False, "dark_patch_albedo": 0.1},
    "2 passes (3, 6 m), open water": {"pass_altitudes": (3.0, 6.0)},
    "2 passes, no open water": {"pass_altitudes": (3.0, 6.0), "open_water": False},
    "2 passes, no open water, darkest 10%": {"pass_altitudes": (3.0, 6.0), "open_water": False,
                                             "dark_patch_albedo": 0.1},
    "2 passes, no open water, no dark patches": {"pass_altitudes": (3.0, 6.0), "open_water": False,
                                                 "num_dark_patches": 0},
    "3 passes (2, 4, 6 m), no open water, darkest 10%": {"pass_altitudes": (2.0, 4.0, 6.0), "open_water": False,
                                                         "dark_patch_albedo": 0.1},
    "2 passes, no open water, darkest 10%, gradient": {"pass_altitudes": (3.0, 6.0), "open_water": False,
                                                       "dark_patch_albedo": 0.1, "medium_profile": "gradient"},
    "2 passes, no open water, darkest 10%, turbid bottom": {"pass_altitudes": (3.0, 6.0), "open_water": False,
                                                            "dark_patch_albedo": 0.1,
                                                            "medium_profile": "turbid-bottom"},
}
# the survey variants, started from the estimate combined by evidence (single-image and multi-view)
MULTIVIEW = ["--model.medium.init", "multiview"]


def survey_name(survey: str) -> str:
    """'2 passes (3, 6 m), open water' -> 'survey-2-passes-3-6-m-open-water'."""
    return "survey-" + re.sub(r"[^a-z0-9]+", "-", survey.lower()).strip("-")


VARIANTS.update({survey_name(survey): (options, MULTIVIEW) for survey, options in SURVEYS.items()})
VARIANTS.update({survey_name(survey) + "-zero-basis": (options, ["medium-grid", *ZERO_BASIS, *MULTIVIEW])
                 for survey, options in SURVEYS.items()
                 if options.get("medium_profile", "homogeneous") != "homogeneous"})
PARAMETERS = ("beta_D", "beta_B", "B_inf")
BAR, GAIN_DB = 0.15, 6.0
FLAT_BAR = 0.05
"""Homogeneous water stays flat when the trained grid's spread over the seabed points (std / mean) is at most this in
every beta and channel: about a tenth of the survey gradient's (the truth's std / mean: 0.34-0.53)."""


def scene_flags(options: dict) -> list[str]:
    """uw-train's datamanager options for SyntheticSceneConfig fields."""
    flags = []
    for key, value in options.items():
        flag = "--datamanager.scene." + key.replace("_", "-")
        if isinstance(value, bool):
            flags.append(flag if value else flag.replace("scene.", "scene.no-"))
        else:
            flags += [flag, *(str(v) for v in (value if isinstance(value, tuple | list) else [value]))]
    return flags


def medium_errors(scene, scene_config: SyntheticSceneConfig, medium, world: torch.Tensor | None = None
                  ) -> dict[str, list[float]]:
    """Per channel relative errors of `medium` (a MediumField, or an estimate: beta_d, beta_b [3], b_inf [3]):
    beta_D, beta_B as fields over world points [N, 3] (default: the seabed points), B_inf against the reference."""
    world = (scene.points if world is None else world).detach().float().cpu()
    true_d, true_b = true_betas(scene, scene_config, world)
    with torch.no_grad():
        learned_d, learned_b = medium.betas(world) if hasattr(medium, "betas") else (medium.beta_d, medium.beta_b)
    truth_inf = torch.tensor(scene.gt.medium["B_inf"], dtype=torch.float64)
    return {"beta_D": ((learned_d.double() - true_d).abs() / true_d).mean(0).tolist(),
            "beta_B": ((learned_b.double() - true_b).abs() / true_b).mean(0).tolist(),
            "B_inf": ((medium.b_inf.detach().double().cpu() - truth_inf).abs() / truth_inf).tolist()}


def field_spread(scene, scene_config: SyntheticSceneConfig, medium) -> dict[str, dict[str, list[float | None]]]:
    """Whether the learned field varies where the truth does: per beta and channel, its mean and standard deviation
    over the seabed points (per dataset unit) and its Pearson correlation with the true field there (None where either
    is flat)."""
    world = scene.points.detach().float().cpu()
    with torch.no_grad():
        learned = [b.double() for b in medium.betas(world)]
    out = {}
    for name, value, truth in zip(("beta_D", "beta_B"), learned, true_betas(scene, scene_config, world), strict=True):
        spread = value.std(0, correction=0) * truth.std(0, correction=0)
        corr = ((value - value.mean(0)) * (truth - truth.mean(0))).mean(0) / spread
        out[name] = {"mean": value.mean(0).tolist(), "std": value.std(0).tolist(), "truth_std": truth.std(0).tolist(),
                     "corr": [float(c) if s > 0 else None for c, s in zip(corr, spread, strict=True)]}
    return out


def true_betas(scene, scene_config: SyntheticSceneConfig, world: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """The true beta_D, beta_B [N, 3] (float64, per dataset unit) at world points [N, 3] of the scene."""
    dataset = world.double() * scene.dataset_scale + torch.tensor(scene.dataset_center, dtype=torch.float64)
    true_d, true_b = beta_field(scene_config, dataset.numpy())
    return torch.as_tensor(true_d), torch.as_tensor(true_b)


def truth_spread(scene, scene_config: SyntheticSceneConfig) -> dict[str, list[float]]:
    """The true field's standard deviation per beta and channel over the seabed points (per dataset unit)."""
    truth = true_betas(scene, scene_config, scene.points.detach().cpu())
    return {name: value.std(0).tolist() for name, value in zip(("beta_D", "beta_B"), truth, strict=True)}


def ray_mean_errors(datamanager, scene_config: SyntheticSceneConfig, ray_betas) -> dict[str, list[float]]:
    """Per channel relative errors of the betas as the images see them: averaged along each test pixel's ray to its
    true surface (`ray_betas(camera, ranges)` -> [H, W, 3] pair, world units) against the true ray mean, over the
    pixels that see the seabed. The medium is scored where the images constrain it (the field read at a ray's
    `--model.medium.ray-samples` points), which the field at the seabed points need not be."""
    scene, reference = datamanager.scene, datamanager.scene.gt.medium
    errors = {"beta_D": [], "beta_B": []}
    for batch in datamanager.test_batches():
        camera, ranges = batch["camera"], batch["range"]
        seen = ranges.isfinite()
        origin = camera.center.double().numpy() * scene.dataset_scale + scene.dataset_center
        factor = torch.as_tensor(ray_mean_factor(scene_config, origin, camera.ray_directions().double().numpy(),
                                                 ranges.double().numpy() * scene.dataset_scale))[seen]
        with torch.no_grad():
            learned = ray_betas(camera, torch.where(seen, ranges, 0.0))
        for name, value in zip(errors, learned, strict=True):
            truth = factor[:, None] * torch.tensor(reference[name], dtype=torch.float64)
            errors[name].append((value[seen].double() - truth).abs() / truth)
    return {name: torch.cat(e).mean(0).tolist() for name, e in errors.items()}


def varying_row(datamanager, scene_config: SyntheticSceneConfig, beta_d: torch.Tensor, beta_b: torch.Tensor,
                b_inf: torch.Tensor, factor: FactorField) -> dict:
    """The field fit's start (fields/medium_varying.py: each beta [3] times `factor`) and its errors at the seabed
    points and along the test rays (the factor's mean along each ray, as the fit reads it)."""
    def betas(world):
        f = factor(world.double()).float()[:, None]
        return beta_d * f, beta_b * f

    def along(camera, ranges):
        dirs = camera.ray_directions().reshape(-1, 3).double()
        start = camera.center.double().expand_as(dirs)
        m = (factor.ray_weights(start, start + dirs * ranges.reshape(-1, 1).double(), 8)
             @ factor.values.reshape(-1)).float().view(*ranges.shape, 1)
        return beta_d * m, beta_b * m

    medium = SimpleNamespace(betas=betas, b_inf=b_inf)
    return {"medium": {"beta_d": beta_d.tolist(), "beta_b": beta_b.tolist(), "b_inf": b_inf.tolist(),
                       "factor": factor.to_json()},
            "errors": medium_errors(datamanager.scene, scene_config, medium),
            "errors_ray_mean": ray_mean_errors(datamanager, scene_config, along)}


def homogeneous_row(datamanager, scene_config: SyntheticSceneConfig, beta_d: torch.Tensor, beta_b: torch.Tensor,
                    b_inf: torch.Tensor) -> dict:
    """A homogeneous medium (each [3]) and its errors at the seabed points and along the test rays."""
    medium = SimpleNamespace(beta_d=beta_d, beta_b=beta_b, b_inf=b_inf)

    def flat(camera, ranges):
        return beta_d.expand(*ranges.shape, 3), beta_b.expand(*ranges.shape, 3)

    return {"medium": {"beta_d": beta_d.tolist(), "beta_b": beta_b.tolist(), "b_inf": b_inf.tolist()},
            "errors": medium_errors(datamanager.scene, scene_config, medium),
            "errors_ray_mean": ray_mean_errors(datamanager, scene_config, flat)}


def evidence_start(evidence: dict, datamanager, scene_config: SyntheticSceneConfig) -> dict:
    """The start of a run with init 'multiview' (its `notes/medium_evidence.json`): the combined medium, its errors,
    and what its evidence does not identify (with why), which replaces the single-image report's verdict."""
    values = {name: torch.tensor([c["value"] for c in evidence["checks"] if c["name"] == name])
              for name in PARAMETERS}
    if evidence.get("factor"):
        factor = FactorField(*(torch.tensor(evidence["factor"][k], dtype=torch.float64)
                               for k in ("center", "axes", "ticks", "values")))
        start = varying_row(datamanager, scene_config, *values.values(), factor)
    else:
        start = homogeneous_row(datamanager, scene_config, *values.values())
    weak = [c for c in evidence["checks"] if c["source"] == NOT_IDENTIFIED]
    return {**start, "weak": [f"{c['name']} {c['channel']}" for c in weak],
            "reasons": [f"{c['name']} {c['channel']}: {c['reason']}" for c in weak],
            "sources": {name: [c["source"] for c in evidence["checks"] if c["name"] == name] for name in PARAMETERS}}


def start_of(row: dict) -> dict:
    """What the run started from: 'medium', 'errors', 'errors_ray_mean', 'weak' (not identifiable before training)
    and 'reasons'; the combined estimate and its evidence for init 'multiview', else the single-image estimate and
    its report."""
    return row.get("start") or {**row["estimate"], "weak": row["weak"], "reasons": row["reasons"]}


def estimate_row(scene_config: SyntheticSceneConfig, cache_dir: Path | None) -> dict:
    """The point-based estimate as `uw3dgs` makes it before training (plain and with the residual term), its errors,
    the identifiability report of the plain one (the default), and the input's PSNR against the clean test images."""
    knobs = METHODS["uw3dgs"].config.model.medium
    datamanager = SyntheticDataManagerConfig(scene=scene_config, cache_dir=cache_dir).setup(data=None)
    scene = datamanager.scene
    row = {}
    for key, residual in (("estimate", False), ("estimate_residual", True)):
        est, water = estimate_from_views(knobs, scene, datamanager.train_indices, residual=residual)
        row[key] = homogeneous_row(datamanager, scene_config, est.beta_d, est.beta_b, est.b_inf)
        if not residual:
            report = assess_medium(*est.observations, est.fit, water, knobs.dark_bins, knobs.dark_share, residual,
                                   positions=est.positions, open_water=est.open_water)
            row["report"] = report.lines()
            row["open_water_reason"] = report.open_water_reason
            row["varies_in_space"] = report.varies_in_space
            row["spatial_disagreement"] = report.spatial_disagreement
            row["weak"] = [f"{c.name} {c.channel}" for c in report.checks if not c.identifiable]
            row["reasons"] = [f"{c.name} {c.channel}: {c.reason}" for c in report.checks if not c.identifiable]
            row["recoverable_range"] = report.recoverable_range
            row["unrecoverable_share"] = report.unrecoverable_share
    clean = [psnr(b["image"], b["clean_image"]) for b in datamanager.test_batches()]
    row["input_psnr"] = float(torch.stack(clean).mean())
    return row


def recoverable_psnr(model, datamanager, reach: list[float]) -> dict[str, float]:
    """The URI and the input judged where the water leaves the clean image recoverable: PSNR (mean over the test
    views) over the seabed pixels and channels c that some training view sees nearer than `reach`[c] (dataset
    units; the report's `recoverable_range`: farther, a typical seabed colour sends under one grey level through the
    water), and the share of the seabed pixel-channels beyond it (occlusion ignored)."""
    scene = datamanager.scene
    cameras = [scene.cameras[i] for i in datamanager.train_indices]
    reach_t = torch.tensor(reach, dtype=torch.float64)
    uri, hazy, beyond, total = [], [], 0, 0
    for batch in datamanager.test_batches():
        camera, ranges = batch["camera"], batch["range"].double()
        seen = ranges.isfinite()
        world = camera.center.double() + camera.ray_directions().double()[seen] * ranges[seen][:, None]
        nearest = torch.full((len(world),), torch.inf, dtype=torch.float64)
        for cam in cameras:
            inside = cam.project(world)[1]
            nearest = torch.where(inside, torch.minimum(nearest, (world - cam.center.double()).norm(dim=-1)), nearest)
        mask = torch.zeros(*ranges.shape, 3, dtype=torch.bool)
        mask[seen] = (nearest * scene.dataset_scale)[:, None] <= reach_t
        beyond += int(seen.sum()) * 3 - int(mask.sum())
        total += int(seen.sum()) * 3
        with torch.no_grad():
            render = model.get_outputs(camera)["uri"].clamp(0, 1)
        clean = batch["clean_image"]
        for store, image in ((uri, render), (hazy, batch["image"])):
            store.append(-10 * torch.log10((image - clean).double().square()[mask].mean()))
    return {"uri_psnr": float(torch.stack(uri).mean()), "input_psnr": float(torch.stack(hazy).mean()),
            "beyond": beyond / max(total, 1)}


def train_and_eval(run_root: Path, argv: list[str], steps: int) -> Path:
    """Train (or continue) and evaluate the run under `run_root`; returns its config.yml."""
    configs = sorted(run_root.glob("**/config.yml"))
    checkpoint = latest_checkpoint(configs[0].parent) if configs else None
    if configs and checkpoint is None:  # killed before its first checkpoint: start again
        shutil.rmtree(configs[0].parent)
    if checkpoint is None:
        train_entrypoint(argv)
        configs = sorted(run_root.glob("**/config.yml"))
    elif checkpoint_step(checkpoint) < steps:
        train_entrypoint(["--load-config", str(configs[0]), "--resume"])
    config = configs[0]
    if not (config.parent / "eval/results.json").is_file():
        from uw3dgs.cli.eval import EvalArgs, run_eval
        run_eval(EvalArgs(load_config=config, save_renders=False), progress=False)
    return config


def same_medium(a: dict, b: dict, tolerance: float = 1e-6) -> bool:
    """Whether two estimates' media (beta_d, beta_b, b_inf lists) agree to `tolerance`."""
    return all(abs(x - y) <= tolerance for k in ("beta_d", "beta_b", "b_inf") for x, y in zip(a[k], b[k], strict=True))


def re_estimate(name: str, output_dir: Path, scene_config: SyntheticSceneConfig, cache_dir: Path | None) -> None:
    """Make the estimate and report of `name` again (after a change to either). A saved row whose estimate is the
    same keeps its trained run and takes the new report; one whose estimate moved is set aside (its run, into
    OUTPUT_DIR/VARIANT.before/) to be trained again from the new estimate."""
    folder = output_dir / name
    row_path, estimate_path = folder / "row.json", folder / "estimate.json"
    new = estimate_row(scene_config, cache_dir)
    folder.mkdir(parents=True, exist_ok=True)
    estimate_path.write_text(json.dumps(new, indent=1))
    if not row_path.is_file():
        return
    row = json.loads(row_path.read_text())
    if same_medium(row["estimate"]["medium"], new["estimate"]["medium"]):
        row.update(new)
        row_path.write_text(json.dumps(row, indent=1))
        return
    aside = output_dir / f"{name}.before"
    aside.mkdir(exist_ok=True)
    for item in folder.iterdir():
        if item.name != "estimate.json":
            shutil.move(str(item), str(aside / item.name))


def run_variant(name: str, steps: int, output_dir: Path, scene_overrides: dict, cache_dir: Path | None,
                train_flags: list[str], estimate_again: bool = False, seed: int = 0) -> dict:
    path = output_dir / name / "row.json"
    options, method_flags = VARIANTS[name]
    scene_config = SyntheticSceneConfig(**{**options, **scene_overrides})
    if estimate_again:
        re_estimate(name, output_dir, scene_config, cache_dir)
    if path.is_file() and json.loads(path.read_text())["steps"] == steps:
        row = json.loads(path.read_text())
        if "recoverable" not in row:  # a row saved before the recoverable range was reported
            config = sorted((output_dir / name).glob("**/config.yml"))[0]
            _, datamanager, model, _ = load_trained(config)
            model.eval()
            row["recoverable"] = recoverable_psnr(model, datamanager, row["recoverable_range"])
            path.write_text(json.dumps(row, indent=1))
        spread = row["trained"].get("spread")
        if spread and "mean" not in spread["beta_D"]:  # a row saved before the field's mean was kept
            _, datamanager, model, _ = load_trained(sorted((output_dir / name).glob("**/config.yml"))[0])
            spread = row["trained"]["spread"] = field_spread(datamanager.scene, scene_config, model.medium)
            path.write_text(json.dumps(row, indent=1))
        if spread and "truth_std" not in spread["beta_D"]:  # a row saved before the true field's spread was kept
            data = SyntheticDataManagerConfig(scene=scene_config, **({"cache_dir": cache_dir} if cache_dir else {}))
            for beta, std in truth_spread(data.setup(data=None).scene, scene_config).items():
                spread[beta]["truth_std"] = std
            path.write_text(json.dumps(row, indent=1))
        return row
    estimate_path = output_dir / name / "estimate.json"
    if estimate_path.is_file():
        row = json.loads(estimate_path.read_text())
    else:
        row = estimate_row(scene_config, cache_dir)
        estimate_path.parent.mkdir(parents=True, exist_ok=True)
        estimate_path.write_text(json.dumps(row, indent=1))
    argv = ["uw3dgs", "--max-num-iterations", str(steps), "--seed", str(seed), "--output-dir", str(output_dir / name),
            "--timestamp", "run", "--no-progress", *method_flags, *train_flags,
            "synthetic", *scene_flags({**options, **scene_overrides}),
            *(["--datamanager.cache-dir", str(cache_dir)] if cache_dir else [])]
    config = train_and_eval(output_dir / name, argv, steps)
    results = json.loads((config.parent / "eval/results.json").read_text())["results"]
    _, datamanager, model, _ = load_trained(config)
    model.eval()
    row.update(name=name, steps=steps, command="uw-train " + " ".join(argv), uri_psnr=results["uri_psnr"],
               trained={"medium": {k: t.tolist() for k, t in model.medium_summary().items()},
                        "errors": medium_errors(datamanager.scene, scene_config, model.medium),
                        "errors_at_centres": medium_errors(datamanager.scene, scene_config, model.medium,
                                                           model.gaussians.means),
                        "errors_ray_mean": ray_mean_errors(datamanager, scene_config, model.ray_betas),
                        "spread": field_spread(datamanager.scene, scene_config, model.medium)},
               eval=results, recoverable=recoverable_psnr(model, datamanager, row["recoverable_range"]))
    evidence = config.parent / NOTES_DIR / "medium_evidence.json"
    if evidence.is_file():
        row["start"] = evidence_start(json.loads(evidence.read_text()), datamanager, scene_config)
    path.write_text(json.dumps(row, indent=1))
    return row


def percents(errors: list[float]) -> str:
    return "/".join(f"{100 * e:.0f}" for e in errors)


def verdict(row: dict) -> tuple[str, str]:
    """(the weak parameters or 'identifiable', whether the bar is met: every parameter and channel the report
    calls identifiable within 15% after training and the URI 6 dB above the input's PSNR on the whole image; if not,
    what missed, a URI short of the bar with its gain on the recoverable seabed too)."""
    weak = set(start_of(row)["weak"])
    misses = [f"{p} {c}" for p in PARAMETERS for c, e in zip("RGB", row["trained"]["errors"][p], strict=True)
              if f"{p} {c}" not in weak and e > BAR]
    gain = row["uri_psnr"] - row["input_psnr"]
    if gain < GAIN_DB:  # the bar is the whole image's; where the water leaves the seabed recoverable, for reference
        there = (f" (+{row['recoverable']['uri_psnr'] - row['recoverable']['input_psnr']:.1f} dB where recoverable)"
                 if "recoverable" in row else "")
        misses.append(f"URI +{gain:.1f} dB{there}")
    weak_text = "; ".join(f"{p} {''.join(c for c in 'RGB' if f'{p} {c}' in weak)}" for p in PARAMETERS
                          if any(f"{p} {c}" in weak for c in "RGB")) or "identifiable"
    rest = " for the rest" if weak else ""
    return weak_text, f"met{rest}" if not misses else f"not met{rest}: " + ", ".join(misses)


def row_label(row: dict) -> str:
    """The row's name in the tables: the variant, with its seed under --seeds."""
    return row.get("label", row["name"])


def table(rows: list[dict]) -> list[str]:
    lines = ["| variant | estimate err % beta_D / beta_B / B_inf (R/G/B) | with residual term | "
             "trained err % beta_D / beta_B / B_inf (R/G/B) | input PSNR | URI PSNR | not identifiable | "
             "bar met |", "|---|---|---|---|---:|---:|---|---|"]
    for row in rows:
        errs = [" ; ".join(percents(part["errors"][p]) for p in PARAMETERS)
                for part in (start_of(row), row["estimate_residual"], row["trained"])]
        weak, met = verdict(row)
        lines.append(f"| {row_label(row)} | {errs[0]} | {errs[1]} | {errs[2]} | "
                     f"{row['input_psnr']:.2f} | {row['uri_psnr']:.2f} | {weak} | {met} |")
    lines.append("")
    lines += [f"- {row_label(row)}: {reason}" for row in rows for reason in start_of(row)["reasons"]]
    return lines


def field_table(rows: list[dict]) -> list[str]:
    """The varying-medium rows: the betas' error in % (R/G/B) at the seabed points, at the trained Gaussian centres,
    and averaged along the test rays (what the images see), the start (the homogeneous estimate) and the end."""
    rows = [row for row in rows if VARIANTS[row["name"]][0].get("medium_profile", "homogeneous") != "homogeneous"]
    if not rows:
        return []
    lines = ["| variant | medium | beta_D: seabed points / Gaussian centres / test rays | beta_B: the same |",
             "|---|---|---|---|"]
    for row in rows:
        for label, part in (("estimate", start_of(row)), ("trained", row["trained"])):
            where = ["errors", "errors_at_centres", "errors_ray_mean"] if label == "trained" else \
                ["errors", None, "errors_ray_mean"]
            cells = [" / ".join(percents(part[w][p]) if w else "-" for w in where) for p in PARAMETERS[:2]]
            lines.append(f"| {row_label(row)} | {label} | {cells[0]} | {cells[1]} |")
    return lines


def spread_table(rows: list[dict]) -> list[str]:
    """The varying-medium rows: how the trained field varies at the seabed points (standard deviation per dataset
    unit, correlation with the true field, '-' for a flat field, and amplitude: its standard deviation over the
    true field's), and the UWI's PSNR against the hazy test images (how well the images are fitted); rows saved
    before the spread was stored are left out."""
    rows = [row for row in rows if VARIANTS[row["name"]][0].get("medium_profile", "homogeneous") != "homogeneous"
            and "spread" in row["trained"]]
    if not rows:
        return []
    lines = ["| variant | beta_D std (R/G/B) | beta_D corr with truth ; amplitude | beta_B std | beta_B corr ; "
             "amplitude | UWI PSNR |", "|---|---|---|---|---|---:|"]
    for row in rows:
        spread = row["trained"]["spread"]
        cells = [cell for p in PARAMETERS[:2] for cell in (
            "/".join(f"{s:.3g}" for s in spread[p]["std"]),
            "/".join("-" if c is None else f"{c:.2f}" for c in spread[p]["corr"]) + " ; " + "/".join(
                f"{s / t:.2f}" if t > 0 else "-" for s, t in zip(spread[p]["std"], spread[p]["truth_std"],
                                                                 strict=True)))]
        lines.append(f"| {row_label(row)} | {' | '.join(cells)} | {row['eval']['psnr']:.2f} |")
    return lines


def trains_grid(name: str) -> bool:
    """Whether variant `name` trains the VM grid (not `medium-homogeneous`)."""
    return "medium-homogeneous" not in VARIANTS[name][1]


def is_homogeneous_grid(row: dict) -> bool:
    """A run of the VM grid in water that is the same everywhere."""
    return trains_grid(row["name"]) and VARIANTS[row["name"]][0].get("medium_profile", "homogeneous") == "homogeneous"


def flat_table(rows: list[dict]) -> list[str]:
    """The VM grid in homogeneous water: its trained spread over the seabed points (std / mean in %, R/G/B) per beta,
    and whether it stays flat (every one at most FLAT_BAR); rows saved before the mean was kept are left out."""
    rows = [row for row in rows if is_homogeneous_grid(row) and "mean" in row["trained"].get("spread", {}).get(
        "beta_D", {})]
    if not rows:
        return []
    lines = ["| variant | beta_D spread % (R/G/B) | beta_B spread % | largest % | flat |", "|---|---|---|---:|---|"]
    for row in rows:
        spread = row["trained"]["spread"]
        ratios = {p: [s / m for s, m in zip(spread[p]["std"], spread[p]["mean"], strict=True)] for p in PARAMETERS[:2]}
        largest = max(max(r) for r in ratios.values())
        cells = " | ".join("/".join(f"{100 * r:.1f}" for r in ratios[p]) for p in PARAMETERS[:2])
        flat = "yes" if largest <= FLAT_BAR else f"no (bar {100 * FLAT_BAR:.0f}%)"
        lines.append(f"| {row_label(row)} | {cells} | {100 * largest:.1f} | {flat} |")
    return lines


def recoverable_table(rows: list[dict]) -> list[str]:
    """How much of the seabed the water leaves recoverable (the report's `recoverable_range`, before training) and
    the URI judged there as well as on the whole image: the input's and the URI's PSNR against the clean test
    images over the seabed pixel-channels some training view sees within that range."""
    lines = ["| variant | recoverable to (R/G/B) | fitted points beyond (%) | test seabed beyond (%) | "
             "input / URI PSNR there | URI - input there (dB) | whole image (dB) |",
             "|---|---|---|---:|---:|---:|---:|"]
    for row in rows:
        rec = row["recoverable"]
        lines.append(f"| {row_label(row)} | {'/'.join(f'{z:.1f}' for z in row['recoverable_range'])} | "
                     f"{percents(row['unrecoverable_share'])} | {100 * rec['beyond']:.0f} | "
                     f"{rec['input_psnr']:.2f} / {rec['uri_psnr']:.2f} | {rec['uri_psnr'] - rec['input_psnr']:+.1f} | "
                     f"{row['uri_psnr'] - row['input_psnr']:+.1f} |")
    return lines


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--steps", type=int, default=3000, help="training steps of every run")
    parser.add_argument("--seeds", type=int, nargs="+", default=None,
                        help="uw-train's --seed: every variant once per seed, in OUTPUT_DIR/sSEED/VARIANT, a row each "
                             "(default: seed 0 in OUTPUT_DIR/VARIANT)")
    parser.add_argument("--variants", nargs="+", choices=list(VARIANTS), default=list(VARIANTS))
    parser.add_argument("--output-dir", type=Path, default=Path("outputs/medium-recovery"))
    parser.add_argument("--scene", action="append", default=[], metavar="KEY=VALUE",
                        help="a SyntheticSceneConfig option for every variant, e.g. width=48")
    parser.add_argument("--cache-dir", type=Path, default=None, help="where scenes are generated (default: uw-train's)")
    parser.add_argument("--estimate-again", action="store_true",
                        help="make every estimate and report again; saved runs whose estimate is unchanged are kept, "
                             "the others set aside (OUTPUT_DIR/VARIANT.before/) and trained again")
    parser.add_argument("--grid-flags", default="", metavar="'FLAGS'",
                        help="uw-train options of the VM grid (--model.medium.*) added to the variants that train it, "
                             "not to the medium-homogeneous ones, one quoted string (e.g. the paper's start: "
                             "--grid-flags='--model.medium.flat-start zero-basis --model.medium.factor-penalty norm "
                             "--model.medium.factor-penalty-weight 0.001')")
    parser.add_argument("--train-flags", default="", metavar="'FLAGS'",
                        help="uw-train method options added to every variant's, one quoted string (a diagnostic, e.g. "
                             "--train-flags='--optimizers.medium-beta.lr 0.01'; give it its own --output-dir)")
    args = parser.parse_args(argv)
    fields = {f.name: f.type for f in dataclasses.fields(SyntheticSceneConfig)}
    overrides = {}
    for item in args.scene:
        key, value = item.split("=", 1)
        overrides[key] = int(value) if fields[key] in (int, "int") else float(value)
    rows = []
    for seed in args.seeds or [0]:
        for name in args.variants:
            grid = shlex.split(args.grid_flags) if trains_grid(name) else []
            row = run_variant(name, args.steps, args.output_dir / f"s{seed}" if args.seeds else args.output_dir,
                              overrides, args.cache_dir, [*grid, *shlex.split(args.train_flags)], args.estimate_again,
                              seed)
            rows.append({**row, "label": f"{name} (seed {seed})"} if args.seeds else row)
    print("\n".join(table(rows) + [""] + recoverable_table(rows) + [""] + field_table(rows) + [""]
                    + spread_table(rows) + [""] + flat_table(rows)))


if __name__ == "__main__":
    main()
