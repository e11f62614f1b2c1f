"""Water that is not there: the verdict's numbers, uw3dgs collapsing to no medium on the built-in scene without water
(and keeping its water on the built-in scene as it is), and uw-eval saying so."""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path

import pytest
import torch
from conftest import run_command

from uw3dgs.cli.eval import entrypoint as uw_eval
from uw3dgs.datamanagers.synthetic import SyntheticDataManagerConfig
from uw3dgs.engine.evaluator import PANEL_LABELS, evaluate_views
from uw3dgs.engine.run_folder import shape_mismatch
from uw3dgs.engine.trainer import Trainer
from uw3dgs.medium.water_verdict import far_range, water_verdict
from uw3dgs.methods.uw3dgs import method as uw3dgs_method
from uw3dgs.utils.images import read_image


def test_verdict_is_optical_depth_against_a_level():
    beta_d, beta_b = torch.tensor([0.01, 0.02, 0.03]), torch.tensor([0.005, 0.0, 0.01])
    verdict = water_verdict(beta_d, beta_b, 2.0, level=0.1)
    assert verdict.depth_d == pytest.approx((0.02, 0.04, 0.06)) and verdict.depth_b == pytest.approx((0.01, 0, 0.02))
    assert verdict.little_water and "little or no water" in verdict.line() and "consider 3dgs" in verdict.line()
    assert not water_verdict(beta_d, beta_b, 2.0, level=0.05).little_water  # one channel above the level is water
    assert not water_verdict(beta_d, beta_b * 10, 2.0, level=0.1).little_water  # backscatter alone counts
    for line in (verdict.line(), water_verdict(beta_d, beta_b, 20.0, 0.1).line()):
        assert "seabed" not in line and "\n" not in line
    assert far_range(torch.arange(101.0)) == pytest.approx(95.0)


def _started_model(cache_dir, scene):
    """A uw3dgs model started from the estimate (without the identifiability report: slow, and not judged here)."""
    dm = SyntheticDataManagerConfig(scene=scene, cache_dir=cache_dir).setup(data=None)
    config = uw3dgs_method.config.model
    config = dataclasses.replace(config, medium=dataclasses.replace(config.medium, report=False))
    model = config.setup(scene=dm.scene, train_indices=dm.train_indices)
    model.initialize_from_data(dm.scene, dm.train_indices)
    return model, dm


def test_a_scene_without_water_collapses_to_no_medium(cache_dir, tiny_scene_config, capsys):
    model, dm = _started_model(cache_dir, dataclasses.replace(tiny_scene_config, medium_strength=0.0))
    err = capsys.readouterr().err
    assert "little or no water" in err and "medium report:" not in err
    assert bool(model.water_free) and not model.renders_medium
    notes = model.run_notes()
    assert notes["water"]["collapsed"] and notes["water"]["little_water"] and "medium_report" not in notes
    with torch.no_grad():
        out = model.eval().get_outputs(dm.cameras[0])
    assert torch.equal(out["rgb"], out["uri"]) and "beta_d" not in out
    assert all(float(v.abs().max()) == 0 for v in model.medium_summary().values())
    # a checkpoint from before the verdict (no 'water_free') loads, as a model that renders its medium
    state = {k: v for k, v in model.state_dict().items() if k != "water_free"}
    assert shape_mismatch(model, {"model": state, "optimizers": dict.fromkeys(model.param_groups())}, None,
                          Path("old.ckpt")) is None  # --resume takes it too
    model.load_checkpoint_state(state)
    assert model.renders_medium


def test_the_built_in_scene_keeps_its_water(cache_dir, tiny_scene_config, capsys, tmp_path):
    model, dm = _started_model(cache_dir, tiny_scene_config)
    err = capsys.readouterr().err
    assert "water: optical depth" in err and "little or no water:" not in err
    assert "of the multi-view fit" not in err  # far above --model.medium.water-check-below: not fitted again
    assert model.renders_medium and not model.run_notes()["water"]["collapsed"]
    with torch.no_grad():
        out = model.eval().get_outputs(dm.cameras[0])
    assert not torch.equal(out["rgb"], out["uri"])
    # the eval compare images of this model: one labelled panel per image, each label documented
    panels = model.get_image_dict(out, dm.get_batch(dm.test_indices[0]))
    assert set(panels) <= set(PANEL_LABELS)
    evaluate_views(model, dm, progress=False, save_dir=tmp_path)
    compare = read_image(tmp_path / "compare" / f"{Path(dm.scene.image_names[dm.test_indices[0]]).stem}.png")
    height, width = dm.scene.images.shape[1:3]
    assert compare.shape[0] > height and compare.shape[1] >= len(panels) * width
    assert compare[: compare.shape[0] - height].max() > 0.5  # white label text on the black strip
    documented = (Path(__file__).resolve().parents[1] / "docs" / "evaluation.md").read_text()
    assert all(f"`{label}`" in documented for label in PANEL_LABELS.values())


@pytest.mark.slow
def test_uw3dgs_on_a_water_free_scene_renders_the_photos_and_says_so(tmp_path, cache_dir, tiny_scene_config, capsys):
    """Trained on the built-in scene without water, the URI is as close to the photos as the UWI (within 0.5 dB,
    here equal: no medium is rendered), and uw-eval repeats the verdict."""
    scene = dataclasses.replace(tiny_scene_config, medium_strength=0.0)
    config = dataclasses.replace(
        uw3dgs_method.config, max_num_iterations=60, output_dir=tmp_path, progress=False, device="cpu",
        timestamp="t", steps_per_save=60, steps_per_eval_image=10**6, steps_per_eval_all_images=10**6,
        datamanager=SyntheticDataManagerConfig(scene=scene, cache_dir=cache_dir))
    trainer = Trainer(config)
    trainer.setup()
    trainer.train()
    code, _, err = run_command(uw_eval, [str(trainer.run_dir / "config.yml"), "--no-save-renders"], capsys)
    assert code == 0 and "little or no water" in err
    results = json.loads((trainer.run_dir / "eval" / "results.json").read_text())
    assert abs(results["results"]["uri_psnr"] - results["results"]["psnr"]) < 0.5
    assert results["water"]["collapsed"]


def _observations(num_points: int, beta_d: float, beta_b: float, seed: int = 0):
    """Points with colours in [0.1, 0.8] seen 5 times each at ranges from 3-8 units to twice that, through a
    homogeneous medium (B_inf 0.4 in every channel), 1% noise: (point ids [M], colours [M, 3], ranges [M])."""
    g = torch.Generator().manual_seed(seed)
    clean = 0.1 + 0.7 * torch.rand(num_points, 3, generator=g, dtype=torch.float64)
    near = 3 + 5 * torch.rand(num_points, 1, generator=g, dtype=torch.float64)
    z = (near * 2 ** torch.linspace(0, 1, 5, dtype=torch.float64)).reshape(-1)
    point = torch.arange(num_points).repeat_interleave(5)
    color = clean[point] * torch.exp(-beta_d * z[:, None]) + 0.4 * (1 - torch.exp(-beta_b * z[:, None]))
    return point, color + 0.01 * torch.randn(color.shape, generator=g, dtype=torch.float64), z


@pytest.mark.parametrize(("beta_d", "beta_b", "dry"), [(0.0, 0.0, True), (0.05, 0.04, False), (0.05, 0.0, False)])
def test_the_multiview_verdict_reads_attenuation_off_how_colours_change_with_range(beta_d, beta_b, dry):
    """Each surface the same colour at every range: beta_D's bootstrap 95% bound stays near 0 and the verdict (over
    ranges to 16 units, level 0.25) is 'little or no water'; through water (optical depth 0.8 at 16 units, with or
    without backscatter) it is not. (beta_B's own fit is no evidence here: on the dry points one channel's lands
    where backscatter saturates at every range, a constant colour the surfaces absorb.)"""
    from uw3dgs.fields.medium_multiview import MultiviewConfig, multiview_estimate

    point, color, z = _observations(300, beta_d, beta_b)
    fit = multiview_estimate(point, color, z, MultiviewConfig(resamples=6), b_inf=torch.full((3,), 0.4))
    assert fit.upper is not None and all(u >= v for u, v in zip(fit.upper[0], fit.fit.beta_d.tolist(), strict=True))
    bound = torch.tensor(fit.upper[0])
    verdict = water_verdict(bound, bound, 16.0, 0.25, source="the multi-view fit")
    assert verdict.little_water == dry, verdict.line()
    assert "of the multi-view fit" in verdict.line() and verdict.to_json()["source"] == "the multi-view fit"


def test_the_multiview_check_overrules_a_single_image_that_reads_water_into_a_dry_scene(cache_dir, tiny_scene_config,
                                                                                          capsys, monkeypatch):
    """The built-in scene without water, its single-image estimate tripled (a single image reading haze into shading,
    as on the real fox photos: docs/evaluation.md): that verdict sees water, the multi-view fit finds no attenuation
    (an optical depth of about 0.14 on this tiny scene), the model collapses to no medium and the notes keep the
    verdict that decided; with the check off (--model.medium.water-check-below 0) the single-image verdict stands.
    The built-in scene with water (optical depths 1.6-5.4) is not checked again: the fit costs tens of seconds."""
    import uw3dgs.methods.uw3dgs.model as model_module

    real = model_module.estimate_from_views

    def hazy(*args, **kwargs):
        estimate, water = real(*args, **kwargs)
        return dataclasses.replace(estimate, beta_d=estimate.beta_d * 3, beta_b=estimate.beta_b * 3), water

    monkeypatch.setattr(model_module, "estimate_from_views", hazy)
    scene = dataclasses.replace(tiny_scene_config, medium_strength=0.0)
    dm = SyntheticDataManagerConfig(scene=scene, cache_dir=cache_dir).setup(data=None)
    for below, collapsed in ((1.0, True), (0.0, False)):
        config = uw3dgs_method.config.model
        # a short bootstrap: the wiring is tested here, the bound's meaning above
        multiview = dataclasses.replace(config.medium.multiview, resamples=2, max_observations=3000)
        medium = dataclasses.replace(config.medium, report=False, water_check_below=below, multiview=multiview)
        model = dataclasses.replace(config, medium=medium).setup(scene=dm.scene, train_indices=dm.train_indices)
        model.initialize_from_data(dm.scene, dm.train_indices)
        err = capsys.readouterr().err
        assert "water: water: optical depth" in err and "of the single-image estimate" in err
        assert bool(model.water_free) == collapsed
        assert ("of the multi-view fit" in model.run_notes()["water"]["line"]) == collapsed


def test_uw_eval_judges_the_learned_medium_again_and_names_each_medium(tiny_uw3dgs_trainer, tmp_path):
    from uw3dgs.cli.eval import EvalArgs, run_eval

    water = run_eval(EvalArgs(load_config=tiny_uw3dgs_trainer.run_dir / "config.yml", save_renders=False,
                              output_path=tmp_path / "results.json"), progress=False)["water"]
    assert water["source"] in ("the single-image estimate", "the multi-view fit (beta_D's 95% bound, for beta_B too)")
    assert water["learned"]["source"] == "the learned medium" and "of the learned medium" in water["learned"]["line"]
    assert water["learned"]["far_range"] == water["far_range"] and water["learned"]["level"] == water["level"]
