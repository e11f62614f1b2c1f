"""End to end: train 3DGS on a tiny synthetic scene, checkpoint, resume, evaluate, fail clearly."""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path

import pytest
import torch
from conftest import as_uw3dgs, train, train_until_killed

from uw3dgs.cli.eval import EvalArgs, run_eval
from uw3dgs.config import load_config
from uw3dgs.engine.checkpoint import list_checkpoints
from uw3dgs.engine.trainer import Trainer, TrainingDivergedError


def test_training_learns_and_writes_the_run_folder(make_config):
    trainer = Trainer(make_config(steps=60, timestamp="t"))
    trainer.setup()
    first = trainer.eval_all(0)["psnr"]
    n0 = trainer.model.num_gaussians
    trainer.train()
    last = trainer.eval_all(60)["psnr"]
    assert last > first + 3.0, (first, last)
    assert trainer.model.num_gaussians != n0  # densification and pruning ran
    run_dir = trainer.run_dir
    assert run_dir.parts[-3:] == ("synthetic", "3dgs", "t")
    assert (run_dir / "config.yml").is_file()
    assert [p.name for p in list_checkpoints(run_dir)] == ["step-000040.ckpt", "step-000060.ckpt"]
    assert list(run_dir.glob("events.out.tfevents.*"))
    saved = load_config(run_dir / "config.yml")
    assert saved == trainer.config
    # a config from another version (an option since removed) names the file, the option and the fix
    stale = run_dir / "stale.yml"
    stale.write_text((run_dir / "config.yml").read_text().replace("  llffhold:", "  old_knob: 1\n  llffhold:", 1))
    with pytest.raises(ValueError, match=r"stale.yml: .*no option\(s\) \['old_knob'\].*delete those lines"):
        load_config(stale)


def test_resume_matches_an_uninterrupted_run(make_config, monkeypatch):
    # opacity reset at step 15 and densification up to 20 both happen before the kill: their state must survive
    from uw3dgs.models.base import Model

    fits = []  # the data-dependent start (e.g. uw3dgs's medium estimate) runs on a fresh run, never on a resume
    hook = Model.initialize_from_data
    monkeypatch.setattr(Model, "initialize_from_data", lambda self, *a: (fits.append(1), hook(self, *a)))
    full = train(make_config(steps=40, reset_opacity_every=15, timestamp="full"))
    assert len(fits) == 1

    config = make_config(steps=40, reset_opacity_every=15, timestamp="killed")
    killed = train_until_killed(config, monkeypatch, step=26)
    assert [p.name for p in list_checkpoints(killed.run_dir)] == ["step-000020.ckpt"]

    resumed = Trainer(dataclasses.replace(config, resume=True))
    resumed.setup()
    assert resumed.start_step == 20 and len(fits) == 2  # the full run's and the killed one's, not the resume's
    resumed.train()
    a, b = full.model.state_dict(), resumed.model.state_dict()
    assert a.keys() == b.keys()
    for key in a:
        assert a[key].shape == b[key].shape, key
        torch.testing.assert_close(a[key], b[key], rtol=1e-5, atol=1e-6, msg=key)


def test_resume_without_checkpoint_is_a_clear_error(make_config):
    with pytest.raises(FileNotFoundError, match="no checkpoint"):
        Trainer(make_config(resume=True, timestamp="never-trained")).setup()


def test_nan_loss_stops_with_a_clear_error_and_keeps_checkpoints(make_config, monkeypatch):
    trainer = Trainer(make_config(steps=40, timestamp="nan"))
    trainer.setup()
    original = trainer.model.get_loss_dict

    def poisoned(outputs, batch, step):
        losses = original(outputs, batch, step)
        return {k: v * float("nan") for k, v in losses.items()} if step == 25 else losses

    monkeypatch.setattr(trainer.model, "get_loss_dict", poisoned)
    with pytest.raises(TrainingDivergedError, match="step 25.*--resume"):
        trainer.train()
    assert [p.name for p in list_checkpoints(trainer.run_dir)] == ["step-000020.ckpt"]


def test_uw_eval_writes_nerfstudio_shaped_json(make_config):
    trainer = train(make_config(steps=20, timestamp="ev"))
    out = trainer.run_dir / "metrics.json"
    run_eval(EvalArgs(load_config=trainer.run_dir / "config.yml", output_path=out))
    data = json.loads(out.read_text())
    assert data["method_name"] == "3dgs" and data["experiment_name"] == "synthetic"
    assert data["checkpoint"].endswith("step-000020.ckpt")
    results = data["results"]
    # the synthetic scene has true ranges: plain 3DGS reports its depth error too, comparable with uw3dgs's
    for key in ("psnr", "psnr_std", "ssim", "ssim_std", "num_gaussians", "depth_abs_rel"):
        assert key in results
    assert results["num_gaussians"] == trainer.model.num_gaussians
    expected = trainer.eval_all(20)
    assert results["psnr"] == pytest.approx(expected["psnr"], abs=1e-4)
    assert len(data["per_image"]) == len(trainer.datamanager.test_indices)
    assert (trainer.run_dir / "eval" / "renders" / "compare").is_dir()
    names = [Path(row["image"]).stem + ".png" for row in data["per_image"]]
    assert sorted(p.name for p in (trainer.run_dir / "eval" / "renders" / "covisible").iterdir()) == sorted(names)


def test_uw_eval_of_an_earlier_checkpoint_goes_beside_the_final_evaluation(make_config):
    trainer = train(make_config(steps=40, timestamp="ev-step"))  # checkpoints at 20 and 40
    config = trainer.run_dir / "config.yml"
    final = run_eval(EvalArgs(load_config=config, save_renders=False))
    earlier = run_eval(EvalArgs(load_config=config, step=20))
    assert final["checkpoint"].endswith("step-000040.ckpt") and earlier["checkpoint"].endswith("step-000020.ckpt")
    assert Path(earlier["output_path"]) == trainer.run_dir / "eval" / "step-000020" / "results.json"
    assert (trainer.run_dir / "eval" / "step-000020" / "renders" / "compare").is_dir()
    assert json.loads((trainer.run_dir / "eval" / "results.json").read_text())["checkpoint"] == final["checkpoint"]
    assert earlier["results"]["psnr"] != final["results"]["psnr"]  # 20 more steps of training changed the render
    with pytest.raises(FileNotFoundError, match=r"no checkpoint of step 30 \(saved: 20, 40\)"):
        run_eval(EvalArgs(load_config=config, step=30))


@pytest.mark.parametrize("name", ["uw3dgs", "uw3dgs-no-medium", "uw3dgs-no-lbeta", "uw3dgs-no-lz"])
def test_uw3dgs_variants_train_and_report_their_metrics(make_config, name):
    trainer = train(as_uw3dgs(make_config(steps=12, timestamp=name), name))
    losses, _ = trainer.train_step(13)
    has_medium = name != "uw3dgs-no-medium"
    assert ("beta_loss" in losses) == (name in ("uw3dgs", "uw3dgs-no-lz"))
    assert ("depth_loss" in losses) == (name in ("uw3dgs", "uw3dgs-no-lbeta"))
    summary = trainer.eval_all(13)
    assert ("uri_psnr" in summary) == has_medium
    assert ("uri_psnr_covisible" in summary) == has_medium
    # the synthetic scene has ground-truth ranges: the co-visible PSNR is measured, over most of each view
    assert "psnr_covisible" in summary and 0.5 < summary["covisible_share"] <= 1.0
    assert ("beta_d_rel_error" in summary) == has_medium
    assert "depth_abs_rel" in summary
