"""`tensorf` and `seathru-nerf` end to end on the tiny synthetic scene, with every schedule shrunk to tens of steps
(grid growth, the alpha mask and its crop, the learning-rate restarts): training, resume, evaluation, uw-render."""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path

import pytest
import torch
from conftest import run_command, train, train_until_killed

from uw3dgs.cli.eval import EvalArgs, run_eval
from uw3dgs.cli.export import entrypoint as export_entrypoint
from uw3dgs.cli.render import entrypoint as render_entrypoint
from uw3dgs.cli.viewer import entrypoint as viewer_entrypoint
from uw3dgs.datamanagers.synthetic import SyntheticDataManagerConfig
from uw3dgs.engine.config import TrainConfig
from uw3dgs.engine.trainer import Trainer
from uw3dgs.registry import METHODS

METHODS_HERE = ("tensorf", "seathru-nerf")


def tiny_config(method: str, output_dir: Path, cache_dir: Path, scene, **overrides) -> TrainConfig:
    """`method` at 128 rays a step on a 10^3 -> 16^3 grid: growth after steps 4 and 12, the mask (and crop) after 8."""
    base: TrainConfig = METHODS[method].config
    model = dataclasses.replace(base.model, batch_size=128, voxels_init=10 ** 3, voxels_final=16 ** 3,
                                upsample_steps=(4, 12), alpha_mask_steps=(8,), render_chunk=2048)
    return dataclasses.replace(base, model=model, max_num_iterations=16, output_dir=output_dir, progress=False,
                               device="cpu", steps_per_save=8, steps_per_eval_image=16, steps_per_eval_all_images=16,
                               datamanager=SyntheticDataManagerConfig(scene=scene, cache_dir=cache_dir), **overrides)


@pytest.mark.slow
@pytest.mark.parametrize("method", METHODS_HERE)
def test_a_short_run_trains_resumes_bit_exact_evaluates_and_renders(method, tmp_path, cache_dir, tiny_scene_config,
                                                                     monkeypatch, capsys):
    full = train(tiny_config(method, tmp_path / "out", cache_dir, tiny_scene_config, timestamp="full"))
    resolution = full.model.field.resolution()
    assert resolution != (10, 10, 10) and full.model.occupancy.built  # it grew, and the mask was built

    config = tiny_config(method, tmp_path / "out", cache_dir, tiny_scene_config, timestamp="killed")
    train_until_killed(config, monkeypatch, step=11)
    resumed = Trainer(dataclasses.replace(config, resume=True))
    resumed.setup()
    assert resumed.start_step == 8
    resumed.train()
    a, b = full.model.state_dict(), resumed.model.state_dict()
    assert a.keys() == b.keys()
    for key in a:
        assert torch.equal(a[key], b[key]), key

    out = tmp_path / "metrics.json"
    run_eval(EvalArgs(load_config=full.run_dir / "config.yml", output_path=out))
    summary = json.loads(out.read_text())["results"]
    assert summary["psnr"] > 10 and summary["depth_abs_rel"] is not None
    if method == "seathru-nerf":
        for key in ("uri_psnr", "uri_uciqe", "uri_uiqm", "beta_d_r", "beta_b_g", "b_inf_b", "beta_d_rel_error",
                    "b_inf_rel_error"):
            assert summary[key] is not None, key

    outputs = "uwi,uri,depth" if method == "seathru-nerf" else "uwi,depth"
    argv = [str(full.run_dir / "config.yml"), "--path", "test", "--outputs", outputs, "--images", str(tmp_path / "f")]
    code, stdout = run_command(render_entrypoint, argv, capsys)[:2]
    assert code == 0, stdout
    assert len(list((tmp_path / "f").rglob("*.png"))) == 2  # the two test views

    code, stdout = run_command(export_entrypoint, [str(full.run_dir / "config.yml"), "--output",
                                                   str(tmp_path / "scene.ply")], capsys)[:2]
    assert code != 0 and "no Gaussians to export as a PLY" in stdout and len(stdout.strip().splitlines()) == 1
    code, stdout = run_command(viewer_entrypoint, [str(full.run_dir / "config.yml"), "--port", "7391"], capsys)[:2]
    assert code != 0 and "uw-render" in stdout and len(stdout.strip().splitlines()) == 1
