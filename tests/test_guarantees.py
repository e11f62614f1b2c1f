"""What docs/training.md ("What is guaranteed") promises: a run folder belongs to one run, --resume continues the
run where its config is and with parameters of the same shapes, no NaN model is saved or evaluated, every numeric
option and config value is checked with its name, output paths fail in one line, and Ctrl-C / SIGTERM stop after a
complete step with its checkpoint. Each case on the tiny synthetic scene, a few steps."""

from __future__ import annotations

import dataclasses
import os
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
import torch
import yaml
from conftest import as_uw3dgs, tiny_train_config, train

from uw3dgs.cli.eval import EvalArgs, print_results, run_eval
from uw3dgs.cli.eval import entrypoint as uw_eval
from uw3dgs.cli.train import entrypoint as uw_train
from uw3dgs.cli.train import parse_config
from uw3dgs.config import config_to_dict, load_config
from uw3dgs.data.colmap_dataset import DatasetError
from uw3dgs.data.seathru_layout import read_seathru_scene
from uw3dgs.datamanagers.synthetic import cached_scene
from uw3dgs.datamanagers.synthetic.cli import entrypoint as uw_synth
from uw3dgs.engine.checkpoint import list_checkpoints, load_checkpoint, nonfinite
from uw3dgs.engine.evaluator import evaluate_views
from uw3dgs.engine.optimizers import ParamGroupConfig
from uw3dgs.engine.run_folder import LOCK_NAME, RunFolderError, RunLock
from uw3dgs.engine.signals import TrainingInterrupted
from uw3dgs.engine.trainer import Trainer, TrainingDivergedError
from uw3dgs.options import OptionError, check_config, deferred_checks
from uw3dgs.strategy import DensificationConfig

TINY_SCENE = ["synthetic", "--datamanager.scene.width", "48", "--datamanager.scene.height", "36",
              "--datamanager.scene.num-views", "12"]


def snapshot(folder: Path) -> dict[str, bytes]:
    return {str(p.relative_to(folder)): p.read_bytes() for p in sorted(folder.rglob("*")) if p.is_file()
            and p.name != LOCK_NAME}


@pytest.fixture(scope="module")
def trained_run(tmp_path_factory, cache_dir, tiny_scene_config) -> Path:
    """A finished 10-step 3dgs run (checkpoints 5 and 10) that tests copy before changing."""
    config = tiny_train_config(tmp_path_factory.mktemp("trained") / "outputs", cache_dir, tiny_scene_config,
                               steps=10, timestamp="done")
    return train(dataclasses.replace(config, steps_per_save=5)).run_dir


def copy_run(run_dir: Path, where: Path) -> Path:
    shutil.copytree(run_dir, where)
    return where


# ----------------------------------------------------------------------------------------------------
# The run folder belongs to one run


def test_an_existing_run_folder_is_never_reused_without_resume(make_config):
    first = train(dataclasses.replace(make_config(steps=10, timestamp="same"), steps_per_save=5))
    before = snapshot(first.run_dir)
    with pytest.raises(RunFolderError, match=r"already holds a run.*--resume.*another --timestamp"):
        Trainer(make_config(steps=10, timestamp="same", seed=1)).setup()
    assert snapshot(first.run_dir) == before  # nothing deleted, nothing overwritten
    # the command line says the same in one line, with the command that continues it
    config = first.run_dir / "config.yml"
    with pytest.raises(SystemExit) as exc:
        uw_train(["--load-config", str(config), "--max-num-iterations", "20"])
    assert exc.value.code == 2 and snapshot(first.run_dir) == before


def test_a_second_training_into_a_held_folder_names_the_holder(make_config, capsys):
    config = make_config(steps=5, timestamp="busy")
    probe = Trainer(config)
    probe.setup()  # takes the folder, as a training running in another process would
    holder = probe.lock.path.read_text()
    assert f"pid {os.getpid()}" in holder
    other = Trainer(dataclasses.replace(config, timestamp="busy"))
    expected = rf"in use by another training \(pid {os.getpid()} on .*another --timestamp"
    with pytest.raises(RunFolderError, match=expected):
        other.setup()
    probe.train()  # ends, and lets the folder go
    assert not probe.lock.held
    RunLock(probe.run_dir).acquire()  # free again (a fresh process could take it)


def test_resume_of_a_copied_run_continues_in_the_copy(trained_run, tmp_path):
    original = snapshot(trained_run)
    copy = copy_run(trained_run, tmp_path / "moved" / "run")
    config = parse_config(["--load-config", str(copy / "config.yml"), "--resume", "--max-num-iterations", "15",
                           "--optimizers.means.lr", "1e-5"])  # a rate may change on resume
    trainer = train(config)
    assert trainer.run_dir == copy and trainer.start_step == 10
    assert [p.name for p in list_checkpoints(copy)] == ["step-000010.ckpt", "step-000015.ckpt"]
    assert snapshot(trained_run) == original  # the original run is untouched
    saved = load_config(copy / "config.yml")
    assert saved.max_num_iterations == 15 and saved.optimizers["means"].lr == 1e-5
    assert saved.resume is False and saved.load_config is None  # how it was started is not saved: no later
    # --load-config of this file inherits --resume, or a folder to resume in
    done = Trainer(parse_config(["--load-config", str(copy / "config.yml"), "--resume"]))  # at 15 of 15 already
    done.setup()
    with pytest.raises(ValueError, match="step-000015.ckpt is at step 15 and --max-num-iterations is 15: nothing "
                                         "left to train"):
        done.train()
    assert not done.lock.held


def test_resume_refuses_options_that_change_parameter_shapes(trained_run, tmp_path):
    copy = copy_run(trained_run, tmp_path / "run")
    before = snapshot(copy)
    config = parse_config(["--load-config", str(copy / "config.yml"), "--resume", "--max-num-iterations", "20",
                           "--model.gaussians.sh-degree", "1", "--model.ssim-lambda", "0.3"])
    with pytest.raises(ValueError, match=r"--resume cannot change the shapes.*--model\.gaussians\.sh-degree \(3 in "
                                         r"the checkpoint, 1 now\) \[gaussians\.shN \[N, 15, 3\] in the checkpoint, "
                                         r"\[N, 3, 3\] now\]") as info:
        Trainer(config).setup()
    assert "ssim-lambda" not in str(info.value)  # changed too, but it does not set a shape
    assert snapshot(copy) == before


def test_resume_refuses_another_medium_naming_the_option(make_config):
    config = as_uw3dgs(dataclasses.replace(make_config(steps=4, timestamp="medium"), steps_per_save=4))
    medium = dataclasses.replace(config.model.medium, resolution=8, components=2)
    run = train(dataclasses.replace(config, model=dataclasses.replace(config.model, medium=medium))).run_dir
    saved = str(run / "config.yml")
    cases = {("medium-homogeneous",): r"--model\.medium \(the subcommand 'medium-grid' in the checkpoint, "
                                      r"'medium-homogeneous' now\)",
             ("--model.medium.resolution", "4"): r"--model\.medium\.resolution \(8 in the checkpoint, 4 now\)",
             ("--model.medium.components", "3"): r"--model\.medium\.components \(2 in the checkpoint, 3 now\)",
             ("--model.medium.no-learn-beta",): r"--model\.medium\.learn-beta \(True in the checkpoint, False now\)"}
    for flags, expected in cases.items():
        config = parse_config(["--load-config", saved, "--resume", "--max-num-iterations", "8", *flags])
        with pytest.raises(ValueError, match=expected):
            Trainer(config).setup()


def test_leftover_temporary_files_are_removed_when_the_run_starts_again(trained_run, tmp_path):
    copy = copy_run(trained_run, tmp_path / "run")
    leftovers = [copy / "checkpoints" / f".step-000015.ckpt.{'a' * 32}.tmp", copy / f".config.yml.{'b' * 32}.tmp"]
    for path in leftovers:
        path.write_bytes(b"")  # what kill -9 during an atomic write leaves
    keep = copy / f".notes.txt.{'c' * 32}.tmp"  # not a file the trainer writes: not its to delete
    keep.write_bytes(b"")
    config = dataclasses.replace(load_config(copy / "config.yml"), load_config=copy / "config.yml", resume=True,
                                 max_num_iterations=11)
    trainer = Trainer(config)
    trainer.setup()
    trainer.close()
    assert not any(p.exists() for p in leftovers) and keep.exists()


# ----------------------------------------------------------------------------------------------------
# Non-finite parameters: never trained on, saved or evaluated


def test_nonfinite_finds_nan_and_infinities_anywhere():
    clean = {"a": torch.zeros(5, 3), "b": [torch.ones(4), torch.zeros(0)], "step": torch.tensor(3)}
    assert nonfinite(clean) == []
    for value in (float("nan"), float("inf"), float("-inf")):
        for index in ((0, 0), (4, 2), (2, 1)):
            t = torch.zeros(5, 3)
            t[index] = value
            assert nonfinite({**clean, "bad": t}) == ["bad"], (value, index)


def test_nonfinite_parameters_stop_the_run_like_a_nonfinite_loss(make_config, monkeypatch):
    """NaN in parameters stops the run at the next check (every --steps-per-log steps, before any evaluation or
    checkpoint): the step, the group, the resume-with-lower-rates advice; no checkpoint with NaN, ever."""
    trainer = Trainer(make_config(steps=40, steps_per_log=5, timestamp="nan-params"))
    trainer.setup()
    original = Trainer.train_step

    def poisons(self, step):
        out = original(self, step)
        if step == 25:  # after the optimizer step of a checked step, before any other forward pass
            with torch.no_grad():
                self.model.gaussians.shN[3, 0, 0] = float("nan")
        return out

    monkeypatch.setattr(Trainer, "train_step", poisons)
    with pytest.raises(TrainingDivergedError, match=r"^step 25: parameters of group\(s\) shN are NaN or infinite .*"
                                                    r"nothing was written for this step.*--resume, after lowering "
                                                    r"those groups' learning rates \(--optimizers\.shN\.lr\)$"):
        trainer.train()
    assert [p.name for p in list_checkpoints(trainer.run_dir)] == ["step-000020.ckpt"]
    assert not nonfinite(load_checkpoint(list_checkpoints(trainer.run_dir)[0])["model"])
    assert not trainer.lock.held
    # a checkpoint is never written with NaN, whoever asks for it
    with pytest.raises(TrainingDivergedError, match=r"step 30: parameters of group\(s\) shN"):
        trainer.save(30)
    assert [p.name for p in list_checkpoints(trainer.run_dir)] == ["step-000020.ckpt"]


def test_a_huge_learning_rate_ends_in_a_clear_error_not_done(make_config):
    base = make_config(steps=20, timestamp="huge-lr")
    optimizers = {**base.optimizers, "scales": dataclasses.replace(base.optimizers["scales"], lr=1e6)}
    # the loss stays finite while the parameters overflow: the parameter check ends the run, not "Done"
    with pytest.raises(TrainingDivergedError, match=r"step \d+: parameters of group\(s\) .*scales.* are NaN") as info:
        train(dataclasses.replace(base, optimizers=optimizers))
    assert "--optimizers.scales.lr" in str(info.value)


def test_uw_eval_refuses_a_model_with_nonfinite_parameters(trained_run, tmp_path, capsys):
    copy = copy_run(trained_run, tmp_path / "run")
    path = list_checkpoints(copy)[-1]
    state = load_checkpoint(path)
    state["model"]["gaussians.means"][0, 0] = float("inf")
    torch.save(state, path)
    with pytest.raises(ValueError, match="gaussians.means are NaN or infinite.*--step"):
        run_eval(EvalArgs(load_config=copy / "config.yml", save_renders=False))
    with pytest.raises(SystemExit) as exc:
        uw_eval([str(copy / "config.yml"), "--no-save-renders"])
    out = capsys.readouterr().out
    assert exc.value.code == 2 and "NaN or infinite" in out and "Traceback" not in out
    assert not (copy / "eval" / "results.json").exists()


def test_a_metric_no_view_can_give_is_reported_missing(trained_run, capsys):
    from uw3dgs.engine.evaluator import load_trained

    _, datamanager, model, _ = load_trained(trained_run / "config.yml")
    original = model.get_eval_metrics
    first = datamanager.test_indices[0]

    def uncovered(outputs, batch, drop=(first,)):  # depth_abs_rel is None where no pixel is covered
        metrics = original(outputs, batch)
        if batch["index"] in drop:
            metrics["depth_abs_rel"] = None
        return metrics

    model.get_eval_metrics = uncovered
    result = evaluate_views(model, datamanager, progress=False)
    rows = result["per_image"]
    assert rows[0]["depth_abs_rel"] is None and all(r["depth_abs_rel"] is not None for r in rows[1:])
    assert result["summary"]["depth_abs_rel"] == pytest.approx(np.mean([r["depth_abs_rel"] for r in rows[1:]]))
    assert result["summary"]["depth_abs_rel_views"] == len(rows) - 1
    model.get_eval_metrics = lambda outputs, batch: uncovered(outputs, batch, drop=datamanager.test_indices)
    summary = evaluate_views(model, datamanager, progress=False)["summary"]
    assert summary["depth_abs_rel"] is None and summary["psnr"] > 0
    print_results({"experiment_name": "x", "method_name": "y", "results": summary, "output_path": "z"})
    assert "missing" in capsys.readouterr().out


# ----------------------------------------------------------------------------------------------------
# Numeric options: checked where declared, named as typed


@pytest.mark.parametrize("flags, message", [
    (["--max-num-iterations", "0"], "--max-num-iterations must be a whole number >= 1, got 0"),
    (["--max-num-iterations", "-5"], "--max-num-iterations must be a whole number >= 1, got -5"),
    (["--steps-per-save", "0"], "--steps-per-save must be a whole number >= 1, got 0"),
    (["--steps-per-log", "0"], "--steps-per-log must be a whole number >= 1, got 0"),
    (["--keep-checkpoints", "0"], "--keep-checkpoints must be a whole number >= 1, got 0"),
    (["--downscale-factor", "0"], "--downscale-factor must be a whole number >= 1, got 0"),
    (["--optimizers.means.lr", "-0.001"], "--optimizers.means.lr must be a finite number >= 0, got -0.001"),
    (["--optimizers.opacities.lr", "nan"], "--optimizers.opacities.lr must be a finite number >= 0, got nan"),
    (["--model.densification.refine-every", "0"], "--model.densification.refine-every must be a whole number >= 1"),
    (["--model.gaussians.sh-degree", "4"], "--model.gaussians.sh-degree must be a whole number >= 0 and <= 3"),
    (["--timestamp", "../x"], "--timestamp must be one folder name"),
    (TINY_SCENE + ["--datamanager.scene.medium-strength", "-5"],
     "--datamanager.scene.medium-strength must be a finite number >= 0, got -5.0"),
])
def test_a_bad_number_is_one_line_naming_the_option(tmp_path, capsys, flags, message):
    with pytest.raises(SystemExit) as exc:
        uw_train(["3dgs", "--output-dir", str(tmp_path / "out"), *flags])
    out = capsys.readouterr().out
    assert exc.value.code == 2 and f"error: {message}" in out, out
    assert "Traceback" not in out and not (tmp_path / "out").exists()


def test_option_checks_live_in_the_configs():
    with pytest.raises(OptionError, match="^lr must be a finite number >= 0, got -1"):
        ParamGroupConfig(-1.0)
    with pytest.raises(OptionError, match="lr must be > 0 when lr_final is set"):
        ParamGroupConfig(0.0, lr_final=1e-5)
    assert ParamGroupConfig(0.0).lr == 0.0  # a frozen group (the oracle medium of docs/methods/uw3dgs.md)
    with pytest.raises(OptionError, match="refine_every"):
        DensificationConfig(refine_every=0)
    with deferred_checks():  # as while parsing: built unchecked, then checked whole, where the path is known
        bad = ParamGroupConfig(-2.0)
    with pytest.raises(OptionError) as info:
        check_config({"optimizers": {"medium_beta": bad}})
    assert str(info.value) == "--optimizers.medium-beta.lr must be a finite number >= 0, got -2.0"
    assert info.value.key == "optimizers.medium_beta.lr"


def test_uw_synth_checks_its_options_and_its_output_folder(tmp_path, capsys):
    with pytest.raises(SystemExit) as exc:
        uw_synth(["--out", str(tmp_path / "scene"), "--medium-strength", "-5"])
    assert exc.value.code == 2
    assert "error: --medium-strength must be a finite number >= 0, got -5.0" in capsys.readouterr().out
    assert not (tmp_path / "scene").exists()
    (tmp_path / "a-file").write_text("x")
    with pytest.raises(SystemExit) as exc:
        uw_synth(["--out", str(tmp_path / "a-file"), "--num-views", "4"])
    out = capsys.readouterr().out
    assert exc.value.code == 2 and f"--out {tmp_path / 'a-file'}: {tmp_path / 'a-file'} is a file" in out


# ----------------------------------------------------------------------------------------------------
# Data and config files


def test_a_nan_row_in_poses_bounds_names_the_file_and_the_row(tmp_path, cache_dir, tiny_scene_config):
    root = shutil.copytree(cached_scene(tiny_scene_config, cache_dir), tmp_path / "scene")
    rows = np.load(root / "poses_bounds.npy")
    rows[3, 5] = np.nan
    np.save(root / "poses_bounds.npy", rows)
    expected = rf"{root / 'poses_bounds.npy'}: row 3 \(counted from 0: image number 4 by file name\) holds NaN"
    with pytest.raises(DatasetError, match=expected):
        read_seathru_scene(root, cache_dir=tmp_path / "cache")
    shutil.rmtree(root / "sparse")  # poses from poses_bounds.npy alone: the same line, not a traceback
    with pytest.raises(DatasetError, match=expected):
        read_seathru_scene(root, cache_dir=tmp_path / "cache")


@pytest.mark.parametrize("old, new, message", [
    ("max_num_iterations: 10", "max_num_iterations: abc", "max_num_iterations: expected an integer, got 'abc'"),
    ("max_num_iterations: 10", "max_num_iterations: 2.5", "max_num_iterations: expected an integer, got 2.5"),
    ("sh_degree: 3", "sh_degree: true", "model.gaussians.sh_degree: expected an integer, got True"),
    ("background: black", "background: pink", "model.background: expected one of 'black', 'white', 'random'"),
    ("data: null", "data: 3", "data: expected a path or null, got 3"),
    ("progress: false", "progress: 0", "progress: expected true or false, got 0"),
    ("max_num_iterations: 10", "max_num_iterations: -3",
     r"max_num_iterations must be a whole number >= 1, got -3 \(the option --max-num-iterations\)"),
    ("seed: 0", "seed: !!python/object/apply:os.system [ls]", r"not valid plain YAML \(line \d+\)"),
])
def test_a_hand_edited_config_names_the_key_the_type_and_the_file(trained_run, tmp_path, old, new, message):
    text = (trained_run / "config.yml").read_text()
    assert old in text
    path = tmp_path / "edited.yml"
    path.write_text(text.replace(old, new, 1))
    with pytest.raises(ValueError, match=rf"^{path}: {message}") as info:
        load_config(path)
    assert "\n" not in str(info.value)


def test_a_config_may_write_numbers_as_yaml_does(trained_run, tmp_path):
    text = (trained_run / "config.yml").read_text()
    path = tmp_path / "edited.yml"
    lr = load_config(trained_run / "config.yml").optimizers["scales"].lr
    path.write_text(text.replace(f"lr: {lr}", "lr: 1e-3", 1))  # YAML 1.1 reads 1e-3 as text
    assert load_config(path).optimizers["scales"].lr == 1e-3


def test_type_names_only_project_and_plugin_classes_and_imports_nothing_else(tmp_path, monkeypatch):
    module = tmp_path / "side_effect_module.py"
    marker = tmp_path / "imported"
    module.write_text(f"open({str(marker)!r}, 'w').close()\nclass Config:\n    pass\n")
    monkeypatch.syspath_prepend(str(tmp_path))
    from uw3dgs.methods.gaussian_splatting import method

    data = config_to_dict(method.config)
    data["_type"] = "side_effect_module.Config"
    path = tmp_path / "config.yml"
    path.write_text(yaml.safe_dump(data, sort_keys=False))
    with pytest.raises(ValueError, match="_type 'side_effect_module.Config' is not a config class of uw3dgs or of a "
                                         "registered plugin"):
        load_config(path)
    assert not marker.exists() and "side_effect_module" not in sys.modules
    # a registered plugin's package may be named: its entry point's top-level package, read without importing it
    from importlib import metadata

    from uw3dgs import config as config_module

    class EntryPoint:
        module = "side_effect_module"

    real = metadata.entry_points
    monkeypatch.setattr(metadata, "entry_points", lambda group=None: [EntryPoint()] if group == "uw3dgs.fields"
                        else real(group=group))
    assert config_module._module_allowed("side_effect_module") and not marker.exists()
    assert not config_module._module_allowed("side_effect_modulex")


# ----------------------------------------------------------------------------------------------------
# Output paths


def test_a_file_shaped_or_unwritable_output_dir_is_one_line(tmp_path, capsys, monkeypatch):
    blocker = tmp_path / "outputs"
    blocker.write_text("not a folder")
    with pytest.raises(SystemExit) as exc:
        uw_train(["3dgs", "--output-dir", str(blocker / "runs"), "--no-progress", *TINY_SCENE])
    out = capsys.readouterr().out
    assert exc.value.code == 2 and f"--output-dir: {blocker} is a file, not a folder" in out, out
    readonly = tmp_path / "readonly"
    readonly.mkdir()
    real_access = os.access
    monkeypatch.setattr(os, "access", lambda p, mode: False if Path(p) == readonly else real_access(p, mode))
    with pytest.raises(SystemExit) as exc:
        uw_train(["3dgs", "--output-dir", str(readonly), "--no-progress", *TINY_SCENE])
    out = capsys.readouterr().out
    assert exc.value.code == 2 and f"--output-dir: {readonly} is not writable" in out, out
    monkeypatch.setattr(os, "access", real_access)
    # what no check foresaw (a folder made read-only mid-run, a full disk) is one line naming the path too

    def denied(self):
        raise PermissionError(13, "Permission denied", str(tmp_path / "x" / "config.yml"))

    monkeypatch.setattr(Trainer, "setup", denied)
    with pytest.raises(SystemExit) as exc:
        uw_train(["3dgs", "--output-dir", str(tmp_path / "x"), "--no-progress", *TINY_SCENE])
    out = capsys.readouterr().out
    assert exc.value.code == 2 and f"{tmp_path / 'x' / 'config.yml'}: Permission denied (not writable" in out
    assert "Traceback" not in out


def test_uw_eval_output_paths_are_checked_before_evaluating(trained_run, tmp_path, capsys, monkeypatch):
    blocker = tmp_path / "file"
    blocker.write_text("x")
    config = str(trained_run / "config.yml")
    with pytest.raises(SystemExit) as exc:
        uw_eval([config, "--output-path", str(blocker / "results.json")])
    out = capsys.readouterr().out
    assert exc.value.code == 2 and f"--output-path {blocker / 'results.json'}: {blocker} is a file" in out
    readonly = tmp_path / "readonly"
    readonly.mkdir()
    real_access = os.access
    monkeypatch.setattr(os, "access", lambda p, mode: False if Path(p) == readonly else real_access(p, mode))
    with pytest.raises(SystemExit) as exc:
        uw_eval([config, "--output-path", str(readonly / "results.json"), "--no-save-renders"])
    out = capsys.readouterr().out
    assert exc.value.code == 2 and f"{readonly} is not writable" in out and "Traceback" not in out


# ----------------------------------------------------------------------------------------------------
# Signals: stop after a complete step, write its checkpoint, say how to resume, exit 130 / 143


def test_sigterm_checkpoints_the_step_and_the_resume_equals_an_uninterrupted_run(make_config, monkeypatch):
    full = train(make_config(steps=30, reset_opacity_every=15, timestamp="full"))
    config = make_config(steps=30, reset_opacity_every=15, timestamp="stopped")
    stopped = Trainer(config)
    stopped.setup()
    original = Trainer.train_step

    def terminated_during_25(self, step):
        if step == 25:
            os.kill(os.getpid(), signal.SIGTERM)  # arrives mid-step: the step still completes
        return original(self, step)

    monkeypatch.setattr(Trainer, "train_step", terminated_during_25)
    with pytest.raises(TrainingInterrupted) as info:
        stopped.train()
    monkeypatch.setattr(Trainer, "train_step", original)
    assert (info.value.signum, info.value.step) == (signal.SIGTERM, 25)
    assert "--resume" in str(info.value)
    assert [p.name for p in list_checkpoints(stopped.run_dir)] == ["step-000020.ckpt", "step-000025.ckpt"]
    assert signal.getsignal(signal.SIGTERM) is signal.SIG_DFL  # handlers are restored after training
    resumed = train(dataclasses.replace(config, resume=True))
    assert resumed.start_step == 25
    a, b = full.model.state_dict(), resumed.model.state_dict()
    assert a.keys() == b.keys()
    for key in a:
        assert torch.equal(a[key], b[key]), key


@pytest.mark.parametrize("signals, code, checkpoint", [(1, 130, True), (2, 130, False)])
def test_ctrl_c_in_uw_train_exits_130_without_a_traceback(tmp_path, cache_dir, capsys, monkeypatch, signals, code,
                                                          checkpoint):
    original = Trainer.train_step

    def interrupted_at_3(self, step):
        if step == 3:
            for _ in range(signals):  # once: stop after this step; twice: stop now (no checkpoint of a half step)
                os.kill(os.getpid(), signal.SIGINT)
        return original(self, step)

    monkeypatch.setattr(Trainer, "train_step", interrupted_at_3)
    with pytest.raises(SystemExit) as exc:
        uw_train(["3dgs", "--output-dir", str(tmp_path), "--timestamp", "t", "--no-progress", "--max-num-iterations",
                  "50", "--model.raster.backend", "torch", *TINY_SCENE, "--datamanager.cache-dir", str(cache_dir)])
    captured = capsys.readouterr()
    assert exc.value.code == code
    run = tmp_path / "synthetic" / "3dgs" / "t"
    assert (run / "checkpoints" / "step-000003.ckpt").is_file() == checkpoint
    said = captured.out + captured.err  # messages go to the shared console (stderr), results to stdout
    assert f"uw-train --load-config {run / 'config.yml'} --resume" in said and "Traceback" not in said


def test_sigterm_to_a_uw_train_process(tmp_path, cache_dir):
    """What a cluster scheduler does: SIGTERM to the process; it ends with 143, a checkpoint and the resume
    command, and no traceback or native stack dump."""
    args = [sys.executable, "-m", "uw3dgs.cli.train", "3dgs", "--output-dir", str(tmp_path), "--timestamp", "t",
            "--no-progress", "--max-num-iterations", "100000", "--steps-per-save", "100000", "--model.raster.backend",
            "torch", *TINY_SCENE, "--datamanager.cache-dir", str(cache_dir)]
    env = {**os.environ, "OMP_NUM_THREADS": "1"}
    env.pop("UW3DGS_DEBUG", None)
    proc = subprocess.Popen(args, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=env)
    try:
        first = proc.stdout.readline()  # printed once setup is done and training starts
        assert first.startswith("uw-train 3dgs"), first + proc.stderr.read()
        time.sleep(0.3)
        proc.send_signal(signal.SIGTERM)
        out, err = proc.communicate(timeout=60)
    finally:
        if proc.poll() is None:
            proc.kill()
    assert proc.returncode == 143, out + err
    run = tmp_path / "synthetic" / "3dgs" / "t"
    (saved,) = list_checkpoints(run)
    said = out + err
    assert f"Stopped by SIGTERM after step {int(saved.stem.removeprefix('step-'))}" in said
    assert "--resume" in said and "Traceback" not in said and "Fatal Python error" not in said
