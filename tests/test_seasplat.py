"""SeaSplat: its losses against hand-computed values, its formation against a float64 evaluation, its schedule, which
parameters each phase trains, and (slow) a short run that trains, evaluates, exports and renders."""

from __future__ import annotations

import dataclasses
import json
import math
from types import SimpleNamespace

import pytest
import torch
from conftest import train

from uw3dgs.methods.seasplat import SeaSplatScheduleConfig, with_schedule
from uw3dgs.methods.seasplat import method as seasplat
from uw3dgs.methods.seasplat_losses import (
    alpha_background,
    backscatter_loss,
    depth_weighted_l1,
    edge_aware_depth_smoothness,
    gray_world,
    normalized_depth,
    saturation,
)
from uw3dgs.methods.seasplat_medium import seasplat_formation

# -- losses against values worked out by hand --


def test_depth_weighted_l1_by_hand():
    pred = torch.tensor([[[0.5, 0.5, 0.5], [1.0, 0.0, 0.2]]])  # [1, 2, 3]
    gt = torch.tensor([[[0.0, 1.0, 0.5], [0.0, 0.0, 0.0]]])
    depth = torch.tensor([[2.0, 0.5]])
    # pixel 1: 2 * (0.5, 0.5, 0) = 1 + 1 + 0; pixel 2: 0.5 * (1, 0, 0.2) = 0.5 + 0 + 0.1; / 6 values
    assert float(depth_weighted_l1(pred, gt, depth)) == pytest.approx((2.0 + 0.6) / 6)


def test_edge_aware_depth_smoothness_by_hand_with_their_signed_weights():
    depth = torch.tensor([[0.0, 1.0], [0.5, 0.5]])
    image = torch.zeros(2, 2, 3)
    image[0, 1] = 0.3  # brightening to the right on row 0: dI/dx = +0.3 there
    image[1, 0] = 0.6  # brightening downward in column 0: dI/dy = +0.6; column 1 darkens: 0 - 0.3
    # x: row 0 |1 e^-0.3|, row 1 |0 e^0| -> mean (e^-0.3 + 0) / 2; y: col 0 |0.5 e^-0.6|, col 1 |-0.5 e^0.3|
    want = math.exp(-0.3) / 2 + (0.5 * math.exp(-0.6) + 0.5 * math.exp(0.3)) / 2
    assert float(edge_aware_depth_smoothness(image, depth)) == pytest.approx(want, rel=1e-6)


def test_alpha_background_is_the_mean_coverage_of_background_coloured_pixels():
    background = torch.tensor([0.1, 0.3, 0.8])
    image = torch.stack([background, background + 0.05, torch.tensor([0.9, 0.9, 0.1])]).reshape(1, 3, 3)
    alpha = torch.tensor([[0.2, 0.6, 1.0]], requires_grad=True)
    loss = alpha_background(image, background, alpha)
    assert float(loss.detach()) == pytest.approx(0.4)  # the first two pixels are within 0.2 sqrt(3) of the background
    loss.backward()
    assert alpha.grad.tolist() == [[0.5, 0.5, 0.0]]
    far = alpha_background(torch.ones(1, 3, 3), torch.zeros(3), alpha)
    assert float(far.detach()) == 0.0


def test_gray_world_and_saturation_by_hand():
    image = torch.tensor([[[0.2, 0.5, 1.0], [0.4, 0.5, -0.2]]])
    # channel means 0.3, 0.5, 0.4 -> ((-0.2)^2 + 0 + (-0.1)^2) / 3
    assert float(gray_world(image)) == pytest.approx((0.04 + 0.01) / 3)
    # above 0.7: 1.0 -> 0.3^2; below 0: -0.2 -> 0.2^2; six values
    assert float(saturation(image, high=0.7)) == pytest.approx((0.09 + 0.04) / 6)


def test_backscatter_loss_by_hand():
    direct = torch.tensor([0.3, -0.1, -0.5, 0.0])
    # positive part: mean relu = 0.3 / 4; negative: SmoothL1(beta 0.2) of 0.1 -> 0.5 0.01 / 0.2 = 0.025, of 0.5
    # -> 0.5 - 0.1 = 0.4; mean over 4 = 0.10625, times 1000
    assert float(backscatter_loss(direct)) == pytest.approx(0.075 + 1000 * 0.10625)
    assert float(backscatter_loss(direct, cost_ratio=0.0)) == pytest.approx(0.075)


def test_normalized_depth_as_their_code_fills_and_stretches_it():
    alpha = torch.tensor([[1.0, 0.5], [0.0, 0.25]])
    depth_sum = torch.tensor([[2.0, 2.0], [0.0, 1.5]])  # expected z: 2, 4, undefined, 6
    z = normalized_depth(depth_sum, alpha)
    assert z.tolist() == [[0.0, 0.5], [1.0, 1.0]]  # the empty pixel takes the largest value, then min-max
    flat = normalized_depth(torch.full((2, 2), 3.0), torch.ones(2, 2))
    assert flat.tolist() == [[1.0, 1.0], [1.0, 1.0]]  # equal min and max: divided by the maximum
    unstretched = normalized_depth(depth_sum, alpha, scale=2.0, min_max=False)
    assert unstretched.tolist() == [[1.0, 2.0], [3.0, 3.0]]


def test_formation_matches_a_float64_evaluation_with_its_clamps():
    g = torch.Generator().manual_seed(0)
    restored = torch.rand(5, 7, 3, generator=g)
    depth = torch.rand(5, 7, generator=g)
    beta_d = torch.tensor([1.1, -0.3, 0.95])  # a negative beta is clamped: no attenuation in that channel
    beta_b = torch.tensor([0.7, 2.0, 0.1])
    b_inf = torch.tensor([0.2, 0.9, 0.95])
    out = seasplat_formation(restored, depth, beta_d, beta_b, b_inf)
    for y in range(5):
        for x in range(7):
            for c in range(3):
                z = float(depth[y, x])
                att = math.exp(-max(float(beta_d[c]) * z, 0.0))
                bs = float(b_inf[c]) * (1 - math.exp(-max(float(beta_b[c]) * z, 0.0)))
                want = min(max(float(restored[y, x, c]) * att + bs, 0.0), 1.0)
                assert float(out["uwi"][y, x, c]) == pytest.approx(want, abs=1e-6)
                assert float(out["backscatter"][y, x, c]) == pytest.approx(bs, abs=1e-6)
    assert torch.equal(out["attenuation"][..., 1], torch.ones(5, 7))


# -- the schedule --


def test_schedule_follows_their_iterations():
    s = SeaSplatScheduleConfig()  # their defaults: medium from 10,000; 1,000 + 2,000 init; 50 every 100
    assert s.phase(10000) == ("warmup", 10000)
    assert s.phase(10001) == ("medium", 10001) and s.phase(11000) == ("medium", 10001)
    assert s.phase(11001) == ("colors", 10001) and s.phase(13001) == ("colors", 10001)  # 2,000 + iteration 10,001
    assert s.phase(13002) == ("gaussians", 10002)
    assert s.phase(13099) == ("gaussians", 10099)  # iterations 10,002..10,099
    assert [s.phase(13100)[0], s.phase(13149)[0]] == ["medium", "medium"]  # 50 medium steps before 10,100
    assert s.phase(13150) == ("gaussians", 10100) and s.phase(13249) == ("gaussians", 10199)
    assert s.phase(13250) == ("medium", 10200)
    # every iteration after the init phases is one ordinary step, in order
    iterations = [it for phase, it in map(s.phase, range(13002, 20000)) if phase == "gaussians"]
    assert iterations == list(range(10002, 10002 + len(iterations)))
    media = sum(s.phase(k)[0] == "medium" for k in range(13002, 13002 + 150 * 20))
    assert media == 20 * 50


def test_a_shorter_run_keeps_their_proportions():
    s = SeaSplatScheduleConfig().for_run(6000)
    assert (s.medium_from, s.medium_init_steps, s.color_init_steps, s.gray_world_from) == (2000, 200, 400, 2000)
    assert (s.medium_every, s.medium_steps) == (100, 50)  # the cadence is not scaled
    assert SeaSplatScheduleConfig().for_run(30000) == dataclasses.replace(SeaSplatScheduleConfig(), reference_steps=0)


# -- which parameters each phase trains --


def seasplat_config(make_config, steps: int, timestamp: str, **schedule: int):
    """The tiny 3DGS test config (conftest) as seasplat, with its densification and this schedule (as given)."""
    base = make_config(steps=steps, timestamp=timestamp)
    model = dataclasses.replace(seasplat.config.model, densification=base.model.densification)
    return with_schedule(dataclasses.replace(base, method_name="seasplat", model=model,
                                             optimizers=seasplat.config.optimizers), reference_steps=0, **schedule)


@pytest.fixture
def seasplat_trainer(make_config):
    from uw3dgs.engine.trainer import Trainer

    trainer = Trainer(seasplat_config(make_config, 8, "phases", medium_from=2, medium_init_steps=2,
                                      color_init_steps=1, medium_every=2, medium_steps=1))
    trainer.setup()
    return trainer


def grads_after_step(trainer, step: int) -> set[str]:
    """Names of the parameter groups that have a gradient after `step`'s backward (the optimizer step is skipped)."""
    seen: set[str] = set()
    original = trainer.optimizers.step

    def record():
        for name, params in trainer.model.param_groups().items():
            if any(p.grad is not None and p.grad.numel() and bool(p.grad.abs().sum() > 0) for p in params):
                seen.add(name)
        original()

    trainer.optimizers.step = record
    trainer.train_step(step)
    trainer.optimizers.step = original
    return seen


def test_each_phase_trains_its_parameters_only(seasplat_trainer):
    t, model = seasplat_trainer, seasplat_trainer.model
    geometry, colors = {"means", "scales", "quats", "opacities"}, {"sh0"}
    medium = {"medium_beta", "medium_b_inf"}
    # schedule: 1-2 warm-up, 3-4 medium, 5-6 colours (the last is iteration 3), 7 medium (before iteration 4, a
    # multiple of medium_every), 8 iteration 4
    assert grads_after_step(t, 1) == geometry | colors | {"background"}
    assert grads_after_step(t, 2) == geometry | colors | {"background"}
    assert not bool(model.medium_started)
    assert grads_after_step(t, 3) == medium
    assert bool(model.medium_started)
    assert grads_after_step(t, 4) == medium
    assert grads_after_step(t, 5) == colors
    assert grads_after_step(t, 6) == colors
    assert grads_after_step(t, 7) == medium
    assert grads_after_step(t, 8) == geometry | colors
    assert model.phase == "gaussians" and model.iteration == 4


def test_the_medium_starts_from_the_learned_background(seasplat_trainer):
    t, model = seasplat_trainer, seasplat_trainer.model
    t.train_step(1)
    t.train_step(2)
    learned = torch.sigmoid(model.background_logit.detach()).clone()
    model.set_phase(3)
    assert torch.allclose(model.medium.b_inf.detach(), learned)
    model.eval()
    with torch.no_grad():
        out = model.get_outputs(t.datamanager.get_batch(t.datamanager.test_indices[0])["camera"])
    assert "backscatter" in out and torch.equal(out["uri"], out["radiance"])


# -- end to end --


@pytest.mark.slow
def test_a_short_seasplat_run_trains_evaluates_exports_and_renders(make_config, tmp_path, capsys):
    from conftest import run_command
    from test_viewer import free_port

    from uw3dgs.cli.eval import EvalArgs, run_eval
    from uw3dgs.cli.export import entrypoint as export_main
    from uw3dgs.cli.render import entrypoint as render_main
    from uw3dgs.cli.viewer import ViewerArgs, start_viewer
    from uw3dgs.medium.formation import Water
    from uw3dgs.viewer.render import render_outputs

    trainer = train(seasplat_config(make_config, 40, "seasplat", medium_from=15, medium_init_steps=5,
                                    color_init_steps=5, medium_every=5, medium_steps=2))
    assert bool(trainer.model.medium_started)
    results = run_eval(EvalArgs(load_config=trainer.run_dir / "config.yml"))["results"]
    for key in ("psnr", "ssim", "uri_psnr", "uri_ssim", "beta_d_r", "beta_b_g", "b_inf_b", "beta_d_rel_error",
                "beta_b_rel_error", "b_inf_rel_error", "depth_abs_rel", "num_gaussians"):
        assert key in results, key
    assert results["psnr"] > 10 and math.isfinite(results["uri_psnr"])
    ply = tmp_path / "scene.ply"
    code, _, _ = run_command(export_main, [str(trainer.run_dir / "config.yml"), "--output", str(ply)], capsys)
    assert code == 0 and ply.stat().st_size > 0
    medium = json.loads((tmp_path / "scene.medium.json").read_text())  # named after the PLY
    assert medium["b_inf"] == pytest.approx(trainer.model.medium.b_inf.tolist(), abs=1e-6)
    assert medium["kind"] == "homogeneous" and "normalised" in medium["meaning"]
    # the viewer's water control: k = 1 is the model's UWI, k = 0 its URI
    model, camera = trainer.model.eval(), trainer.datamanager.get_batch(0)["camera"]
    with torch.no_grad():
        own = model.get_outputs(camera)
    assert torch.equal(render_outputs(model, camera, Water(k=1.0))["rgb"], own["rgb"])
    assert torch.equal(render_outputs(model, camera, Water(k=0.0))["rgb"], own["uri"])
    murky = render_outputs(model, camera, Water(k=3.0, b_inf=(0.0, 0.0, 1.0)))
    assert not torch.equal(murky["rgb"], own["rgb"])
    # uw-viewer on the run: the medium's outputs and the water control, and a client's view rendered through them
    viewer = start_viewer(ViewerArgs(load_config=trainer.run_dir / "config.yml", port=free_port(), device="cpu"))
    try:
        assert viewer.output.options == ("UWI", "URI", "depth", "attenuation", "backscatter")
        assert viewer.water() == Water(k=1.0, b_inf=None)
        client = SimpleNamespace(camera=SimpleNamespace(wxyz=(1.0, 0.0, 0.0, 0.0), position=(0.0, 0.0, -3.0), fov=1.0,
                                                        aspect=4 / 3, image_width=64, image_height=48),
                                 scene=SimpleNamespace(set_background_image=lambda image, **_: shown.append(image)))
        shown: list = []
        assert viewer.render_client(client) and shown[0].shape[2] == 3
    finally:
        viewer.stop()
    images = tmp_path / "frames"
    code, _, err = run_command(render_main, [str(trainer.run_dir / "config.yml"), "--path", "test",
                                             "--images", str(images)], capsys)
    assert code == 0, err
    assert len(list(images.rglob("*.png"))) >= 1


def test_a_background_other_than_black_is_a_clear_error():
    from uw3dgs.methods.seasplat import SeaSplatModelConfig
    from uw3dgs.options import OptionError

    with pytest.raises(OptionError, match="learns its background"):
        dataclasses.replace(SeaSplatModelConfig(), background="white")


@pytest.mark.slow
def test_a_resume_mid_schedule_matches_an_uninterrupted_run(make_config, monkeypatch):
    from conftest import train_until_killed

    from uw3dgs.engine.trainer import Trainer

    schedule = {"medium_from": 12, "medium_init_steps": 4, "color_init_steps": 4, "medium_every": 3,
                "medium_steps": 2}
    full = train(seasplat_config(make_config, 30, "full", **schedule))
    config = seasplat_config(make_config, 30, "killed", **schedule)
    train_until_killed(config, monkeypatch, step=24)  # checkpoint at 20: the medium started, in the colour phase
    resumed = Trainer(dataclasses.replace(config, resume=True))
    resumed.setup()
    assert resumed.start_step == 20 and bool(resumed.model.medium_started)
    resumed.train()
    a, b = full.model.state_dict(), resumed.model.state_dict()
    assert a.keys() == b.keys()
    for key in a:
        torch.testing.assert_close(a[key], b[key], rtol=1e-5, atol=1e-6, msg=key)
