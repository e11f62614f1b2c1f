"""`uw-train` parsing: nerfstudio's option names, every knob reachable, --load-config, clear errors."""

from __future__ import annotations

import dataclasses
from pathlib import Path

import pytest
import yaml

from uw3dgs.cli.train import entrypoint, parse_config
from uw3dgs.config import MOVED_CLASSES, config_from_dict, config_to_dict, load_config, save_config
from uw3dgs.data.datamanager import AutoDataManagerConfig
from uw3dgs.datamanagers.synthetic import SyntheticDataManagerConfig
from uw3dgs.methods.gaussian_splatting import method as gaussian_splatting
from uw3dgs.registry import METHODS


def test_nerfstudio_option_names(tmp_path):
    config = parse_config([
        "3dgs", "--data", str(tmp_path), "--downscale-factor", "4", "--max-num-iterations", "123",
        "--output-dir", "runs", "--experiment-name", "exp", "--timestamp", "ts", "--steps-per-save", "7",
        "--steps-per-eval-image", "8", "--steps-per-eval-all-images", "9"])
    assert config.method_name == "3dgs"
    assert (config.data, config.downscale_factor, config.max_num_iterations) == (tmp_path, 4, 123)
    assert (config.output_dir, config.experiment_name, config.timestamp) == (Path("runs"), "exp", "ts")
    assert (config.steps_per_save, config.steps_per_eval_image, config.steps_per_eval_all_images) == (7, 8, 9)
    assert isinstance(config.datamanager, AutoDataManagerConfig)


def test_nested_knobs_and_datamanager_subcommand():
    config = parse_config(["3dgs", "--model.gaussians.sh-degree", "2", "--optimizers.means.lr", "0.001",
                           "--model.densification.grad-threshold", "0.001", "synthetic",
                           "--datamanager.scene.width", "64"])
    assert config.model.gaussians.sh_degree == 2
    assert config.optimizers["means"].lr == 0.001
    assert config.model.densification.grad_threshold == 0.001
    assert isinstance(config.datamanager, SyntheticDataManagerConfig)
    assert config.datamanager.scene.width == 64


def test_help_lists_methods_and_knobs(capsys):
    with pytest.raises(SystemExit):
        entrypoint(["--help"])
    assert "3dgs" in capsys.readouterr().out
    with pytest.raises(SystemExit):
        entrypoint(["3dgs", "--help"])
    out = capsys.readouterr().out
    for flag in ("--max-num-iterations", "--load-config", "--resume", "--model.ssim-lambda",
                 "--model.densification.refine-every", "--optimizers.opacities.lr"):
        assert flag in out, flag


def test_yaml_round_trip_of_every_method(tmp_path):
    for name, spec in METHODS.items():
        path = tmp_path / f"{name}.yml"
        save_config(spec.config, path)
        assert config_from_dict(config_to_dict(spec.config)) == spec.config
        assert "!!python" not in path.read_text()


def test_load_config_supplies_defaults_and_flags_override(tmp_path):
    saved = dataclasses.replace(gaussian_splatting.config, max_num_iterations=77, timestamp="old",
                                datamanager=SyntheticDataManagerConfig())
    path = tmp_path / "config.yml"
    save_config(saved, path)
    config = parse_config(["--load-config", str(path), "--steps-per-save", "5"])
    assert config.method_name == "3dgs"
    assert (config.max_num_iterations, config.timestamp, config.steps_per_save) == (77, "old", 5)
    assert config.load_config == path
    assert isinstance(config.datamanager, SyntheticDataManagerConfig)


def test_a_config_saved_before_a_class_moved_still_loads(tmp_path):
    """Run folders name config classes by module path; a class that moved (MOVED_CLASSES) loads under its old name."""
    data = config_to_dict(gaussian_splatting.config)
    assert data["model"]["densification"]["_type"] in MOVED_CLASSES.values()
    data["model"]["densification"]["_type"] = "uw3dgs.fields.densification.DensificationConfig"  # before 9255722
    path = tmp_path / "config.yml"
    path.write_text(yaml.safe_dump(data, sort_keys=False))
    assert load_config(path) == gaussian_splatting.config


def test_unknown_yaml_key_is_an_error(tmp_path):
    data = config_to_dict(gaussian_splatting.config)
    data["max_num_iteration"] = 3
    with pytest.raises(ValueError, match="max_num_iteration"):
        config_from_dict(data)


def test_missing_data_folder_is_a_clear_error(tmp_path, capsys):
    # a long path with brackets: it must come out whole (not wrapped) and literally (not read as markup)
    missing = tmp_path / ("a-long-folder-name-" * 6) / "[dive 3]" / "nope"
    with pytest.raises(SystemExit) as exc:
        entrypoint(["3dgs", "--data", str(missing), "--output-dir", str(tmp_path)])
    assert exc.value.code == 2
    out = capsys.readouterr().out
    assert f"{missing} does not exist" in out
