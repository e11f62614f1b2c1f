"""`watersplatting`: its density-control options (absolute gradients, the late cull), the medium MLP's optimizer
rules (gradient clipping, moments reset after a cull), its losses, the water it reports, and a short run."""

from __future__ import annotations

import dataclasses
import math

import pytest
import torch
from test_densification import make
from test_floaters import plane_scene

from uw3dgs.engine.optimizers import Optimizers, ParamGroupConfig
from uw3dgs.fields import direction_medium
from uw3dgs.fields.direction_medium import DirectionMedium, DirectionMediumConfig, _SigmoidMLP
from uw3dgs.fields.gaussians import PARAM_NAMES
from uw3dgs.methods.watersplatting import (
    MediumResettingDensityControl,
    WaterSplattingModelConfig,
    watersplatting_optimizers,
)
from uw3dgs.metrics.image import ssim
from uw3dgs.registry import METHODS
from uw3dgs.render import RasterSettings
from uw3dgs.render.sh import sh_basis
from uw3dgs.strategy import DefaultStrategy, DensificationConfig


def test_absgrad_option_accumulates_the_absolute_sums():
    """With absgrad the statistics read the renderer's absolute per-pixel sums (as NDC, like 3DGS's gradient), not
    means2d.grad; without them the option is an error, not a silent fallback."""
    _, _, strategy, state = make(refine_stop=100, absgrad=True)
    means2d = torch.zeros(4, 2, requires_grad=True)
    means2d.sum().backward()  # a gradient that must not be read
    absgrad = torch.tensor([[1.0, 2.0], [0.0, 0.0], [3.0, 4.0], [0.5, 0.5]])
    strategy.step_post_backward(state, 10, means2d, torch.tensor([1, 0, 1, 1]), (40, 20), absgrad)
    expected = torch.tensor([math.hypot(20, 20), 0.0, math.hypot(60, 40), math.hypot(10, 5)])
    torch.testing.assert_close(state["grad_accum"], expected)
    with pytest.raises(ValueError, match="absgrad"):
        strategy.step_post_backward(state, 10, means2d, torch.tensor([1, 0, 1, 1]), (40, 20))


def test_late_cull_after_densification_stops():
    """late_min_opacity prunes transparent Gaussians on the densification cadence after refine_stop, nowhere else;
    without it (3DGS) nothing is pruned there."""
    for late, expected in ((0.5, 3), (None, 4)):
        field, optimizers, strategy, state = make(refine_stop=100, late_min_opacity=late)
        assert strategy.prunes_at(200) == (late is not None) and not strategy.prunes_at(150)
        strategy.step_post_optimizer(field, optimizers, state, 150)
        assert field.num_gaussians == 4
        strategy.step_post_optimizer(field, optimizers, state, 200)
        assert field.num_gaussians == expected  # the one of opacity sigmoid(-8) goes
        assert all(optimizers.optimizers[n].state[getattr(field, n)]["exp_avg"].shape[0] == expected
                   for n in PARAM_NAMES)


def test_refine_stop_share_caps_the_schedule():
    def stop(steps: int, **config) -> int:
        return DefaultStrategy(DensificationConfig(**config), 1.0, steps).refine_stop

    assert [stop(s) for s in (6000, 6001, 30000)] == [3000, 3000, 15000]  # the default: half, as before
    recipe = METHODS["watersplatting"].config.model.densification
    assert stop(15000, refine_stop=recipe.refine_stop, refine_stop_share=recipe.refine_stop_share) == 10000
    assert stop(6000, refine_stop=recipe.refine_stop, refine_stop_share=recipe.refine_stop_share) == 4002


def test_gradient_clipping_per_group():
    a, b = torch.nn.Parameter(torch.zeros(3)), torch.nn.Parameter(torch.zeros(2))
    optimizers = Optimizers({"a": ParamGroupConfig(0.1, max_grad_norm=1e-3), "b": ParamGroupConfig(0.1)},
                            {"a": [a], "b": [b]}, 1.0, 10)
    (a * torch.tensor([3.0, 4.0, 0.0])).sum().backward()
    (b * torch.tensor([3.0, 4.0])).sum().backward()
    optimizers.step()
    torch.testing.assert_close(a.grad.norm(), torch.tensor(1e-3))
    torch.testing.assert_close(b.grad, torch.tensor([3.0, 4.0]))  # no max_grad_norm: untouched


def test_medium_moments_reset_when_gaussians_may_be_culled():
    field, optimizers, strategy, state = make(refine_start=100, refine_every=100, refine_stop=1000)
    mlp = torch.nn.Linear(2, 3)
    optimizers.configs["medium_mlp"] = ParamGroupConfig(1e-3)
    optimizers.base_lr["medium_mlp"] = 1e-3
    optimizers.optimizers["medium_mlp"] = torch.optim.Adam(mlp.parameters(), lr=1e-3)
    callback = MediumResettingDensityControl(strategy, field, optimizers, ("medium_mlp",))

    def moments() -> float:
        mlp(torch.ones(1, 2)).sum().backward()
        optimizers.optimizers["medium_mlp"].step()
        return sum(float(s["exp_avg"].abs().sum()) for s in optimizers.optimizers["medium_mlp"].state.values())

    assert moments() > 0
    callback.after_step(150, {}, {})  # no event: kept
    assert moments() > 0
    before = moments()
    callback.after_step(200, {}, {})
    after = sum(float(s["exp_avg"].abs().sum()) for s in optimizers.optimizers["medium_mlp"].state.values())
    assert before > 0 and after == 0.0


def test_direction_medium_encoding_and_ranges():
    medium = DirectionMedium(DirectionMediumConfig())
    dirs = torch.nn.functional.normalize(torch.randn(50, 3, generator=torch.Generator().manual_seed(0)), dim=-1)
    assert sh_basis(3, dirs).shape == (50, 16)
    color, bs, attn = medium(dirs)
    assert color.shape == bs.shape == attn.shape == (50, 3)
    assert ((color > 0) & (color < 1)).all() and (bs > 0).all() and (attn > 0).all()
    layers = [m for m in medium.mlp if isinstance(m, torch.nn.Linear)]
    assert [(m.in_features, m.out_features) for m in layers] == [(16, 128), (128, 9)]


@pytest.mark.parametrize("num_layers,rows_per_block", [(1, 2048), (2, 2048), (2, 8), (3, 16)])
def test_direction_medium_mlp_equals_the_module_with_its_gradients(num_layers: int, rows_per_block: int,
                                                                   monkeypatch: pytest.MonkeyPatch) -> None:
    """The feature-major MLP with its hand-written backward (what `DirectionMedium` runs) is its nn.Sequential:
    outputs, weight and input gradients in float64, and gradcheck; in one block of rows and in several (the last
    one shorter)."""
    monkeypatch.setattr(direction_medium, "ROWS_PER_BLOCK", rows_per_block)
    torch.manual_seed(0)
    medium = DirectionMedium(DirectionMediumConfig(num_layers=num_layers, hidden_dim=8)).double()
    x = torch.randn(37, 16, dtype=torch.float64, requires_grad=True)
    weights = torch.randn(37, 9, dtype=torch.float64)
    params = [p for layer in medium.mlp if isinstance(layer, torch.nn.Linear) for p in (layer.weight, layer.bias)]
    got = _SigmoidMLP.apply(x, *params)
    want = medium.mlp(x)
    torch.testing.assert_close(got, want, rtol=1e-12, atol=1e-12)
    got_grads = torch.autograd.grad((got * weights).sum(), [x, *params])
    want_grads = torch.autograd.grad((want * weights).sum(), [x, *params])
    for g, w in zip(got_grads, want_grads, strict=True):
        torch.testing.assert_close(g, w, rtol=1e-12, atol=1e-12)
    small = [t.detach()[:10].clone().requires_grad_(True) if i == 0 else t for i, t in enumerate([x, *params])]
    assert torch.autograd.gradcheck(lambda *a: _SigmoidMLP.apply(*a), small, fast_mode=True)


@pytest.mark.parametrize("density_bias", [0.0, 19.5])  # 19.5: raw values on both sides of softplus's threshold 20
def test_direction_medium_outputs_and_gradients_are_the_modules(density_bias: float) -> None:
    """c_med, sigma_bs, sigma_attn (packed into one tensor, as the compositor reads them) and their gradients equal
    sigmoid / softplus of the nn.Sequential's outputs, in float64."""
    torch.manual_seed(1)
    medium = DirectionMedium(DirectionMediumConfig(hidden_dim=8, density_bias=density_bias)).double()
    with torch.no_grad():
        medium.mlp[-1].bias[3:] += torch.linspace(-1.0, 1.0, 6, dtype=torch.float64)
    dirs = torch.nn.functional.normalize(torch.randn(6, 5, 3, dtype=torch.float64), dim=-1)
    raw = medium.mlp(sh_basis(3, dirs))
    sigmas = torch.nn.functional.softplus(raw[..., 3:] + density_bias)
    want = (torch.sigmoid(raw[..., :3]), sigmas[..., :3], sigmas[..., 3:])
    got = medium(dirs)
    weights = [torch.randn(6, 5, 3, dtype=torch.float64) for _ in range(3)]
    params = list(medium.parameters())
    for g, w in zip(got, want, strict=True):
        torch.testing.assert_close(g, w, rtol=1e-12, atol=1e-12)
    got_grads = torch.autograd.grad(sum((t * w).sum() for t, w in zip(got, weights, strict=True)), params)
    want_grads = torch.autograd.grad(sum((t * w).sum() for t, w in zip(want, weights, strict=True)), params)
    for g, w in zip(got_grads, want_grads, strict=True):
        torch.testing.assert_close(g, w, rtol=1e-12, atol=1e-12)


def _model():
    scene, *_ = plane_scene()
    # the compiled rasterizer: the slow test; min_train_size 0: the coarse start on these small views too
    config = WaterSplattingModelConfig(raster=RasterSettings(backend="torch"), min_train_size=0)
    return scene, config.setup(scene=scene, train_indices=list(range(1, len(scene.cameras))))


def test_losses_are_divided_by_the_stopped_prediction():
    """reg-L1 and reg-D-SSIM for constant images: L1 |gt - p| / (p + eps), SSIM of gt / (p + eps) and p / (p + eps);
    the gradient sees the denominator as a constant."""
    _, model = _model()
    pred = torch.full((20, 24, 3), 0.5, requires_grad=True)
    gt = torch.full((20, 24, 3), 0.25)
    outputs = {"rgb": pred, "downscale": 1}
    loss = model.get_loss_dict(outputs, {"image": gt}, 0)["rgb_loss"]
    scale = 0.5 + 1e-3
    similarity = float(ssim(torch.full_like(gt, 0.5 / scale), torch.full_like(gt, 0.25 / scale)))
    expected = 0.8 * 0.25 / scale + 0.2 * (1 - similarity)
    assert abs(float(loss.detach()) - expected) < 1e-5
    loss.backward()
    l1_part = 0.8 / scale / pred.numel()  # d|p - gt| / dp / (p + eps), the denominator not differentiated
    assert torch.all(pred.grad > 0) and abs(float(pred.grad[10, 12, 0]) - l1_part) / l1_part < 0.2


def test_training_renders_below_full_resolution_first():
    scene, model = _model()
    camera = scene.cameras[1]
    model.train()
    for step, factor in ((0, 4), (2999, 4), (3000, 2), (6000, 1), (9000, 1)):
        model.set_step(step)
        out = model.get_outputs(camera)
        assert out["downscale"] == factor and out["rgb"].shape == (camera.height // factor, camera.width // factor, 3)
    model.eval()
    assert model.get_outputs(camera)["rgb"].shape == (camera.height, camera.width, 3)


def test_coarse_start_never_trains_below_the_minimum_size():
    """Their 1/4 start is kept where it leaves at least min_train_size pixels on the longer side (1,383 px: 345) and
    lowered where it would not (691 px: 1/2; 172 px, IUI3-RedSea at x8: full resolution); 0 keeps num_downscales."""
    config = WaterSplattingModelConfig()
    assert [config.downscales_for(side) for side in (1383, 1200, 1199, 691, 345, 172)] == [2, 2, 1, 1, 0, 0]
    assert dataclasses.replace(config, min_train_size=0).downscales_for(172) == 2
    scene, _ = _model()
    side = max(scene.cameras[0].width, scene.cameras[0].height)
    model = dataclasses.replace(config, raster=RasterSettings(backend="torch"), min_train_size=side // 2).setup(
        scene=scene, train_indices=list(range(1, len(scene.cameras))))
    model.train()
    model.set_step(0)
    assert model.num_downscales == 1 and model.downscale_factor() == 2


def test_resolution_schedule_scales_with_the_run_length():
    """Their 3,000 steps a doubling are for 15,000 steps: a 6,000-step run doubles every 1,200 (full resolution from
    step 2,400, 60% of the run as theirs); reference_steps 0 keeps 3,000; the callbacks set the run's schedule."""
    config = WaterSplattingModelConfig()
    assert config.resolution_schedule_for_run(15000) == 3000
    assert config.resolution_schedule_for_run(6000) == 1200
    assert config.resolution_schedule_for_run(3) == 1
    assert dataclasses.replace(config, reference_steps=0).resolution_schedule_for_run(6000) == 3000
    _, model = _model()
    optimizers = Optimizers(watersplatting_optimizers(), model.param_groups(), 1.0, 6000)
    model.get_training_callbacks(optimizers, 6000)
    model.train()
    for step, factor in ((0, 4), (1199, 4), (1200, 2), (2399, 2), (2400, 1)):
        model.set_step(step)
        assert model.downscale_factor() == factor


def test_water_summary_is_per_range_and_per_dataset_unit():
    """The eval keys: c_med, and sigma / |ray| / dataset scale, averaged over the test pixels; rel errors against
    the truth. A constant water (bias only) makes the averages known."""
    scene, model = _model()
    with torch.no_grad():
        last = model.direction_medium.mlp[-1]
        last.weight.zero_()
        last.bias.copy_(torch.tensor([0.0, 1.0, -1.0, 0.1, 0.2, 0.3, 0.4, 0.5, 0.6]))
    summary = model.get_eval_summary(scene)
    test = scene.cameras[0]
    mean_inverse_norm = float((1.0 / test.ray_norms()).mean())
    softplus, bias = torch.nn.functional.softplus, last.bias.detach()
    for channel, i in zip("rgb", range(3), strict=True):
        assert abs(summary[f"b_inf_{channel}"] - float(torch.sigmoid(bias[i]))) < 1e-6
        for name, offset in (("beta_b", 3), ("beta_d", 6)):
            want = float(softplus(bias[offset + i])) * mean_inverse_norm / scene.dataset_scale
            assert abs(summary[f"{name}_{channel}"] - want) < 1e-5 * want
    truth = scene.gt.medium["B_inf"]
    b_inf = torch.sigmoid(bias[:3])
    want = float(((b_inf - torch.tensor(truth)).abs() / torch.tensor(truth)).max())
    assert abs(summary["b_inf_rel_error"] - want) < 1e-6


def test_viewing_and_export_interface():
    """render_view: the model's own image at k = 1, the URI at k = 0, murkier water at k = 2, a replaced colour;
    export_medium: the averages and the direction grid; veiling_light: an RGB in [0, 1]."""
    from types import SimpleNamespace

    scene, model = _model()
    camera = scene.cameras[0]
    model.eval()
    with torch.no_grad():
        own = model.get_outputs(camera)
        view = model.render_view(camera)
        assert torch.equal(view["rgb"], own["rgb"]) and torch.equal(view["uri"], own["uri"])
        clear = model.render_view(camera, SimpleNamespace(k=0.0, b_inf=None))
        assert torch.equal(clear["rgb"], own["uri"]) and not clear["backscatter"].any()
        murky = model.render_view(camera, SimpleNamespace(k=2.0, b_inf=None))
        assert (murky["attenuation"] <= view["attenuation"]).all() and not torch.equal(murky["rgb"], view["rgb"])
        red = model.render_view(camera, SimpleNamespace(k=1.0, b_inf=(1.0, 0.0, 0.0)))
        assert (red["backscatter"][..., 1:] == 0).all() and (red["backscatter"][..., 0] > 0).all()
    light = model.veiling_light()
    assert light.shape == (3,) and ((light > 0) & (light < 1)).all()
    exported = model.export_medium((0.0, 0.0, 0.0), scene.dataset_scale, 4)
    assert exported["kind"] == "direction" and len(exported["b_inf"]) == 3
    assert len(exported["c_med"]) == 4 and len(exported["c_med"][0]) == 8 and len(exported["longitudes"]) == 8


@pytest.mark.slow
def test_short_run_trains_evaluates_exports_renders(tmp_path, cache_dir, tiny_scene_config, capsys, monkeypatch):
    """30 steps on the tiny synthetic scene with every schedule shrunk (quarter resolution first, densification,
    an opacity reset, the late cull; culls at 0.02: 5 steps cannot raise an opacity from 0.1 to 0.5): uw-eval
    reports the UWI, the URI and the water with its errors; uw-export writes the PLY; uw-render the test views'
    UWI, URI and range."""
    import json

    from conftest import run_command, tiny_train_config, train

    from uw3dgs.cli.eval import entrypoint as eval_entrypoint
    from uw3dgs.cli.export import entrypoint as export_entrypoint
    from uw3dgs.cli.render import entrypoint as render_entrypoint

    monkeypatch.setenv("COLUMNS", "300")
    spec = METHODS["watersplatting"].config
    model = dataclasses.replace(
        spec.model, resolution_schedule=10, reference_steps=0, min_train_size=0,
        densification=dataclasses.replace(spec.model.densification, refine_start=5, refine_every=5, refine_stop=15,
                                          reset_opacity_every=10, min_opacity=0.02, late_min_opacity=0.02),
        gaussians=dataclasses.replace(spec.model.gaussians, sh_degree_interval=10))
    base = tiny_train_config(tmp_path, cache_dir, tiny_scene_config, steps=30)
    config = dataclasses.replace(base, method_name="watersplatting", model=model, optimizers=spec.optimizers,
                                 steps_per_save=30, steps_per_eval_image=30, steps_per_eval_all_images=30)
    trainer = train(config)
    run = trainer.run_dir / "config.yml"
    assert trainer.model.num_gaussians > 0

    code, out, err = run_command(eval_entrypoint, [str(run)], capsys)
    assert code == 0, out + err
    summary = json.loads((trainer.run_dir / "eval" / "results.json").read_text())["results"]
    for key in ("psnr", "uri_psnr", "beta_d_r", "beta_b_g", "b_inf_b", "beta_d_rel_error", "b_inf_rel_error"):
        assert summary[key] is not None and math.isfinite(summary[key]), key
    assert summary["psnr"] > 10

    ply = tmp_path / "scene.ply"
    code, out, err = run_command(export_entrypoint, [str(run), "--output", str(ply)], capsys)
    assert code == 0 and ply.stat().st_size > 0, out + err

    frames = tmp_path / "frames"
    code, out, err = run_command(render_entrypoint, [str(run), "--path", "test", "--outputs", "uwi,uri,depth",
                                                      "--images", str(frames)], capsys)
    assert code == 0, out + err
    assert sorted(p.name for p in frames.iterdir()) == ["0000.png", "0008.png"]
