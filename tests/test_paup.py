"""PAUP: the statistics U and P against hand values, gradients through the relaxed mask, hard pruning of a planted
floater, the statistics following densification and resume, and the no-paup ablation equal to the branch never
starting."""

from __future__ import annotations

import copy
import dataclasses
import math

import pytest
import torch
from conftest import as_uw3dgs, train, train_until_killed

from uw3dgs.cameras import Camera
from uw3dgs.data.scene import SceneData
from uw3dgs.engine.optimizers import Optimizers
from uw3dgs.engine.trainer import Trainer
from uw3dgs.kernels import build as kernel_build
from uw3dgs.methods.gaussian_splatting import COVERAGE_EPS
from uw3dgs.methods.uw3dgs import UW3DGSModelConfig, uw3dgs_optimizers
from uw3dgs.methods.uw3dgs.paup import PAUP, FloaterScorer, PAUPConfig, combine_views, observe_view, relaxed_keep_mask
from uw3dgs.strategy import DefaultStrategy, DensityControl


def tiny_uw3dgs(make_config, name: str = "uw3dgs", steps: int = 30, paup_start: int = 5, **paup):
    """The tiny 3DGS schedule (densify from 10 every 10) on a uw3dgs variant, PAUP from `paup_start` every 5."""
    config = as_uw3dgs(make_config(steps=steps, timestamp=f"{name}-{paup_start}"), name)
    return dataclasses.replace(config, model=dataclasses.replace(config.model, paup=PAUPConfig(start=paup_start,
                                                                                                every=5, **paup)))


# -- the statistics --

def test_u_and_p_against_hand_values():
    """Two Gaussians, three views on a 2 x 2 image whose rendered range is 4 everywhere. A is seen in every view
    (effective opacities 0.5, 0.5, 0.2; one colour), B only in view 0 (0.9 over 3 pixels; red, green, blue)."""
    surface, alpha = torch.full((2, 2), 4.0), torch.ones(2, 2)
    opacities, beta_d, scale = torch.tensor([0.8, 0.6]), torch.tensor([[0.1, 0.2, 0.3]] * 2), 2.0
    own = torch.tensor([4.0, 2.0])
    radii = torch.tensor([1, 1])
    views = []
    for k, (weights, counts, b_color) in enumerate([((1.0, 0.9), (2, 3), (1.0, 0.0, 0.0)),
                                                    ((0.5, 0.0), (1, 0), (0.0, 1.0, 0.0)),
                                                    ((0.4, 0.0), (2, 0), (0.0, 0.0, 1.0))]):
        colors = torch.tensor([[0.2, 0.4, 0.6], list(b_color)])
        b_pixel = (1.5, 1.5) if k == 0 else (5.0, 5.0)  # outside the image in views 1 and 2
        means2d = torch.tensor([[0.5, 0.5], list(b_pixel)])
        views.append(observe_view(torch.tensor(weights), torch.tensor(counts), colors, means2d, radii, own, surface,
                                  alpha, opacities, beta_d, scale, COVERAGE_EPS))
    u, p, measured = combine_views(views, opacity_weight=0.4, color_weight=0.6)

    var_a = ((0.5 - 0.4) ** 2 + (0.5 - 0.4) ** 2 + (0.2 - 0.4) ** 2) / 3  # population variance over the 3 views
    var_b = ((0.3 - 0.1) ** 2 + 0.1 ** 2 + 0.1 ** 2) / 3
    color_var_b = 2.0 / 3.0  # ||(1,0,0) - (1/3,1/3,1/3)||^2 = 2/3 in each view
    attenuation = [1 - sum(math.exp(-b * d * scale) for b in (0.1, 0.2, 0.3)) / 3 for d in (4.0, 2.0)]
    torch.testing.assert_close(u, torch.tensor([0.4 * var_a, 0.4 * var_b + 0.6 * color_var_b]))
    # A sits on the surface in all three views; B, at range 2 under a surface at 4 (median 4), in view 0 only
    torch.testing.assert_close(p, torch.tensor([0.8 * attenuation[0], 2.0 / 4.0 + 0.6 * attenuation[1]]))
    assert measured.tolist() == [True, True]


def test_a_gaussian_no_view_holds_is_not_measured_and_scores_neutral():
    surface, alpha = torch.full((2, 2), 4.0), torch.ones(2, 2)
    view = observe_view(torch.tensor([1.0, 0.0]), torch.tensor([2, 0]), torch.zeros(2, 3),
                        torch.tensor([[0.5, 0.5], [9.0, 9.0]]), torch.tensor([1, 0]), torch.tensor([4.0, 4.0]),
                        surface, alpha, torch.ones(2), None, 1.0, COVERAGE_EPS)
    _, _, measured = combine_views([view, view], 0.4, 0.6)
    assert measured.tolist() == [True, False]

    paup = PAUP(PAUPConfig(normalize_scores=False), num_gaussians=4)
    paup.update(torch.tensor([0.1, 0.3, 0.2, 9.0]), torch.tensor([1.0, 3.0, 2.0, 9.0]),
                torch.tensor([True, True, True, False]))
    u, p = paup.filled()
    assert u.tolist() == pytest.approx([0.1, 0.3, 0.2, 0.2]) and p.tolist() == [1.0, 3.0, 2.0, 2.0]  # medians
    normalized = PAUP(PAUPConfig(), num_gaussians=3)
    normalized.update(torch.tensor([1.0, 2.0, 6.0]), torch.tensor([0.5, 1.0, 3.0]), torch.ones(3, dtype=torch.bool))
    assert normalized.uncertainty.tolist() == pytest.approx([1 / 3, 2 / 3, 2])  # in units of their mean
    assert normalized.implausibility.tolist() == pytest.approx([1 / 3, 2 / 3, 2])


def test_depth_weights_read_u_as_measured_not_normalised():
    """(1 - U) with U the measured variance (in [0, 0.25]): unit-mean U would give the Gaussian above the mean a
    weight of 0. Unmeasured Gaussians get the measured ones' median."""
    paup = PAUP(PAUPConfig(), num_gaussians=4)
    paup.update(torch.tensor([0.01, 0.02, 0.06, 5.0]), torch.ones(4), torch.tensor([True, True, True, False]))
    assert paup.uncertainty[2] == pytest.approx(2.0)  # the score's unit-mean U
    assert paup.depth_weights().tolist() == pytest.approx([0.99, 0.98, 0.94, 0.98])


def test_the_monotone_phi_never_falls_as_the_score_rises_whatever_its_parameters():
    pus = torch.linspace(0.0, 12.0, 200)
    for monotone in (True, False):
        scorer = FloaterScorer(hidden_units=32, init_weight=0.5, init_score=4.0, init_sharpness=2.0,
                               monotone=monotone)
        with torch.no_grad():  # what training might make of it: negative output weights among others
            for param in scorer.phi.parameters():
                param.add_(torch.randn(param.shape, generator=torch.Generator().manual_seed(1)))
            scorer.phi[2].weight.fill_(-0.1)
        steps = scorer(pus).diff()
        if monotone:
            assert bool((steps >= 0).all())
        else:  # the paper's unconstrained phi can turn around
            assert bool((steps < 0).any())
    with torch.no_grad():  # the plain phi's penalty is that of its parameters
        penalty, by_hand = scorer.weight_penalty(), sum(p.square().sum() for p in scorer.phi.parameters())
    assert float(penalty) == pytest.approx(float(by_hand))


@pytest.mark.parametrize(("dtype", "tolerance"), [(torch.float64, 1e-12), (torch.float32, 1e-5)])
@pytest.mark.parametrize("monotone", [True, False])
def test_compiled_phi_matches_pytorch(dtype, tolerance, monotone):
    """The compiled phi against the PyTorch path in float64: m and the gradients of the scores and of every weight,
    relative to each tensor's largest value; bitwise the same with 1 and 2 threads. A third of the Gaussians get no
    gradient (in training most: kept whole or out of view), which the backward skips."""
    torch.manual_seed(0)
    scorer = FloaterScorer(32, 0.5, 4.0, 2.0, monotone).double()
    with torch.no_grad():  # units that switch on and off across the scores
        for p in scorer.phi.parameters():
            p.add_(0.3 * torch.randn_like(p))
    pus = torch.rand(40_000, dtype=torch.float64) * 8
    weights = torch.randn(40_000, dtype=torch.float64)
    weights[::3] = 0.0

    def run(compiled: bool, dtype: torch.dtype) -> list[torch.Tensor]:
        model = copy.deepcopy(scorer).to(dtype)
        model.kernels = "compiled" if compiled else "torch"
        x = pus.to(dtype, copy=True).requires_grad_()
        (model(x) * weights.to(dtype)).sum().backward()
        return [model(x).detach(), x.grad, *(p.grad for p in model.phi.parameters())]

    reference = run(False, torch.float64)
    threads, runs = torch.get_num_threads(), []
    try:
        for n in (1, 2):
            torch.set_num_threads(n)
            runs.append(run(True, dtype))
    finally:
        torch.set_num_threads(threads)
    for a, b in zip(runs[0], reference, strict=True):
        assert float((a.double() - b).abs().max()) <= tolerance * float(b.abs().max())
    assert all(torch.equal(a, b) for a, b in zip(runs[0], runs[1], strict=True))


def test_compiled_phi_gradients_against_finite_differences():
    from uw3dgs.kernels.paup_scorer import FloaterMLP

    torch.manual_seed(0)
    x = (torch.rand(20, dtype=torch.float64) * 4).requires_grad_()
    w1, b1, w2, b2 = (torch.randn(n, dtype=torch.float64, requires_grad=True) for n in (8, 8, 8, 1))
    assert torch.autograd.gradcheck(FloaterMLP.apply, (x, w1, b1, w2, b2))
    assert PAUP(PAUPConfig(), 3, "torch").scorer.kernels == "torch"
    assert PAUP(PAUPConfig(), 3).scorer.kernels == "compiled"


def test_phi_starts_rising_with_the_score_at_its_stated_midpoint():
    scorer = FloaterScorer(hidden_units=32, init_weight=0.5, init_score=4.0, init_sharpness=2.0)
    pus = torch.tensor([0.0, 1.0, 4.0, 6.0])
    torch.testing.assert_close(scorer(pus), torch.sigmoid(2.0 * (pus - 4.0)))
    torch.testing.assert_close(scorer.w_u, torch.tensor(0.5))
    rng = torch.get_rng_state()
    FloaterScorer(32, 0.5, 4.0, 2.0)
    assert torch.equal(rng, torch.get_rng_state())  # building it draws nothing from the run's generator


def test_relaxed_keep_mask_gradient_matches_finite_differences():
    p = torch.tensor([0.1, 0.5, 0.93], dtype=torch.float64, requires_grad=True)
    torch.manual_seed(3)
    s = relaxed_keep_mask(p, temperature=0.5)
    (grad,) = torch.autograd.grad(s.sum(), p)
    eps = 1e-6
    for i in range(3):
        shifted = [p.detach().clone() for _ in range(2)]
        shifted[0][i] += eps
        shifted[1][i] -= eps
        values = []
        for q in shifted:
            torch.manual_seed(3)  # the same uniform draws
            values.append(relaxed_keep_mask(q, temperature=0.5)[i])
        assert float(grad[i]) == pytest.approx(float((values[0] - values[1]) / (2 * eps)), rel=1e-5)
    assert ((s > 0) & (s < 1)).all()


def test_relaxed_keep_mask_draws_bernoulli_of_the_keep_probability():
    """Hardened at 1/2 the relaxed draws are Bernoulli(p) draws (a wrong sign or scale of the noise breaks it); a
    lower temperature puts them nearer 0 and 1."""
    torch.manual_seed(0)
    p = torch.tensor([0.02, 0.3, 0.5, 0.9, 0.999]).repeat(100_000, 1)
    for temperature in (0.5, 2.0):
        kept = (relaxed_keep_mask(p, temperature) > 0.5).float().mean(0)
        torch.testing.assert_close(kept, p[0], atol=0.005, rtol=0)
    cold, warm = relaxed_keep_mask(p, 0.1), relaxed_keep_mask(p, 2.0)
    assert float((cold - 0.5).abs().mean()) > float((warm - 0.5).abs().mean()) + 0.2


# -- a planted floater on a plane --

HEIGHT = 3.0


def look_down(x: float, y: float, width: int = 40, height: int = 30, focal: float = 40.0) -> Camera:
    # camera at (x, y, HEIGHT) looking down -z: x right, y flipped, z forward
    viewmat = torch.eye(4)
    viewmat[:3, :3] = torch.diag(torch.tensor([1.0, -1.0, -1.0]))
    viewmat[:3, 3] = -viewmat[:3, :3] @ torch.tensor([x, y, HEIGHT])
    K = torch.tensor([[focal, 0, width / 2], [0, focal, height / 2], [0, 0, 1.0]])
    return Camera(viewmat, K, width, height)


def planted_floater_model(mask: str = "expected", **paup):
    """An opaque plane of small Gaussians that all three downward cameras see whole, and one opaque Gaussian 0.5
    below camera 0 and to its side, inside view 0 only, in open water there (the last Gaussian). It hides no part
    of the plane: a Gaussian of the plane hidden in one view is as view-inconsistent as the floater by U and P
    (docs/methods/uw3dgs.md, "What PAUP's statistics see")."""
    xs = torch.arange(-0.4, 0.4001, 0.05)  # well inside every view: no Gaussian of it is cut by an image border
    gx, gy = torch.meshgrid(xs, xs, indexing="ij")
    plane = torch.stack([gx.reshape(-1), gy.reshape(-1), torch.zeros(gx.numel())], dim=-1)
    floater = torch.tensor([[-0.2, 0.0, HEIGHT - 0.5]])
    means = torch.cat([plane, floater])
    cameras = [look_down(0.0, 0.0), look_down(0.6, 0.0), look_down(0.0, 0.6)]
    scene = SceneData(name="plane", image_names=["0", "1", "2"], images=torch.zeros(3, 30, 40, 3), cameras=cameras,
                      points=means, point_colors=torch.full_like(means, 0.5), near=0.1, far=10.0)
    config = UW3DGSModelConfig(paup=PAUPConfig(**{"num_views": 3, "start": 0, "mask": mask, **paup}))
    model = config.setup(scene=scene, train_indices=[0, 1, 2])
    with torch.no_grad():
        model.gaussians.scales.copy_(torch.log(torch.cat([torch.full((len(plane), 3), 0.03),
                                                           torch.full((1, 3), 0.03)])))
        model.gaussians.opacities.fill_(torch.logit(torch.tensor(0.99)).item())
    return model, cameras


def test_compiled_paup_step_matches_pytorch():
    """`--model.kernels compiled` (phi compiled, the masked render and its L1 fused) against `torch` (phi in
    PyTorch, a frozen render and PyTorch's L1): the same I_UR^Enh, L_PAPSL and scorer gradients to rounding."""
    results = []
    for kernel in ("compiled", "torch"):
        model, cameras = planted_floater_model()
        model.paup.scorer.kernels = kernel
        model.paup.fused_masked_l1 = kernel == "compiled"
        model.train()
        model.paup.set_step(0)
        outputs = model.get_outputs(cameras[0])
        fused = type(outputs["uri_enhanced_l1"].grad_fn).__name__ == "_MaskedL1Backward"
        assert fused == (kernel == "compiled" and kernel_build.is_available())
        loss = model.get_loss_dict(outputs, {"camera": cameras[0], "image": torch.zeros(30, 40, 3)}, step=0)
        loss["paup_loss"].backward()
        scorer = model.paup.scorer
        results.append([outputs["uri_enhanced"].detach(), loss["paup_loss"].detach(), scorer.raw_w_u.grad,
                        scorer.raw_w_p.grad, *(p.grad for p in scorer.phi.parameters())])
    assert float(results[0][2].abs()) > 0
    for got, want in zip(*results, strict=True):
        torch.testing.assert_close(got, want, rtol=1e-5, atol=1e-7)


def test_a_planted_floater_gets_the_highest_m_and_is_pruned_at_the_next_event():
    model, cameras = planted_floater_model()
    n = model.num_gaussians
    assert [int(model.render(c)["pixel_count"][-1] > 0) for c in cameras] == [1, 0, 0]  # only view 0 sees it
    model.refresh_paup_statistics(cameras[0])
    assert bool(model.paup.measured.all())
    m = model.paup.scores()[1].detach()
    assert int(m.argmax()) == n - 1 and float(m[-1]) > 0.5
    assert float(m[:-1].max()) < 0.5

    optimizers = Optimizers(uw3dgs_optimizers(paup=True), model.param_groups(), model.scene_extent, 1000)
    control = DensityControl(DefaultStrategy(model.config.densification, model.scene_extent, 1000), model.gaussians,
                             optimizers, extra_pruning=model.paup)
    plane = model.gaussians.means[:-1].detach().clone()
    control.after_step(500, {"camera": cameras[0]}, {})
    assert model.num_gaussians == n - 1 and torch.equal(model.gaussians.means.detach(), plane)
    assert int(model.paup.pruned_total) == 1 and model.paup.pruned_share == pytest.approx(1 / n)
    assert len(model.paup.uncertainty) == n - 1  # the statistics followed
    for name in ("means", "opacities"):  # so did the Adam state (none yet) and the optimizer's parameters
        assert optimizers.optimizers[name].param_groups[0]["params"][0] is getattr(model.gaussians, name)


@pytest.mark.parametrize("after", [False, True])
def test_after_densification_the_floater_is_pruned_only_with_the_late_pruning_knob(after):
    model, cameras = planted_floater_model(prune_after_densification=after)
    model.refresh_paup_statistics(cameras[0])
    n = model.num_gaussians
    optimizers = Optimizers(uw3dgs_optimizers(paup=True), model.param_groups(), model.scene_extent, 1000)
    strategy = DefaultStrategy(model.config.densification, model.scene_extent, 1000)  # densifies up to step 500
    control = DensityControl(strategy, model.gaussians, optimizers, extra_pruning=model.paup)
    scales = model.gaussians.scales.detach().clone()
    control.after_step(550, {"camera": cameras[0]}, {})  # off the cadence: nothing either way
    assert model.num_gaussians == n
    control.after_step(600, {"camera": cameras[0]}, {})
    assert model.num_gaussians == (n - 1 if after else n)
    assert int(model.paup.pruned_total) == int(after) and len(model.paup.uncertainty) == model.num_gaussians
    assert torch.equal(model.gaussians.scales.detach(), scales[:model.num_gaussians])  # nothing split or cloned
    assert optimizers.optimizers["means"].param_groups[0]["params"][0] is model.gaussians.means


def test_statistics_follow_densification():
    paup = PAUP(PAUPConfig(normalize_scores=False), num_gaussians=3)
    paup.update(torch.tensor([0.1, 0.2, 0.3]), torch.tensor([1.0, 2.0, 3.0]), torch.ones(3, dtype=torch.bool))
    paup.reindex(torch.tensor([0, 2, -1, -1]))  # 1 removed, two new ones
    assert paup.uncertainty.tolist() == pytest.approx([0.1, 0.3, 0.0, 0.0])
    assert paup.raw_uncertainty.tolist() == pytest.approx([0.1, 0.3, 0.0, 0.0])
    assert paup.measured.tolist() == [True, True, False, False]
    assert int(paup.created_total) == 5
    assert paup.select(step=0) is None or not bool(paup.select(step=0)[2:].any())  # never the unmeasured ones


@pytest.mark.parametrize("mask", ["expected", "concrete"])
def test_gradients_reach_the_scorer_through_the_mask_and_eval_renders_without_it(mask):
    model, cameras = planted_floater_model(mask)
    model.train()
    model.paup.set_step(0)  # the statistics are due
    outputs = model.get_outputs(cameras[1])
    assert bool(model.paup.has_statistics) and "uri_enhanced" in outputs
    with torch.no_grad():  # the UWI is formed from the full I_UR, the one evaluation renders
        plain = model.render(cameras[1], depth_weights=model.depth_weights())["radiance"]
        keep = 1.0 - model.paup.scores()[1]
        expected = model.render(cameras[1], keep=keep)["radiance"]
    torch.testing.assert_close(outputs["uri"].detach(), plain)
    if mask == "expected":  # deterministic: I_UR^Enh is the render with the opacities times 1 - m
        torch.testing.assert_close(outputs["uri_enhanced"].detach(), expected)
    losses = model.get_loss_dict(outputs, {"camera": cameras[1], "image": torch.zeros(30, 40, 3)}, step=0)
    assert "paup_loss" in losses
    # L_PAPSL trains the scorer alone: its gradient reaches no Gaussian parameter
    gaussian_params = list(model.gaussians.parameters())
    grads = torch.autograd.grad(losses["paup_loss"], gaussian_params, retain_graph=True, allow_unused=True)
    assert all(g is None or not bool(g.any()) for g in grads)
    sum(losses.values()).backward()
    scorer = model.paup.scorer
    for name, param in [("w_u", scorer.raw_w_u), ("w_p", scorer.raw_w_p), *scorer.phi.named_parameters()]:
        assert param.grad is not None and torch.isfinite(param.grad).all(), name
    assert float(scorer.raw_w_u.grad.abs()) > 0 and float(scorer.raw_w_p.grad.abs()) > 0
    assert float(scorer.phi[2].weight.grad.abs().sum()) > 0

    model.eval()
    with torch.no_grad():
        first, second = model.get_outputs(cameras[1]), model.get_outputs(cameras[1])
        plain = model.render(cameras[1], depth_weights=model.depth_weights())
    assert "uri_enhanced" not in first
    assert torch.equal(first["uri"], second["uri"]) and torch.equal(first["uri"], plain["radiance"])


@pytest.mark.parametrize("every", [1, 2])
def test_the_masked_render_every_n_steps_from_start_and_pus_weights_l_beta_on_all(monkeypatch, every):
    """--model.paup.enhanced-every N: I_UR^Enh, m and L_PAPSL on every N-th step from PAUP's start (every step for
    N = 1, the paper); the steps between still give L_beta its PUS weights, train nothing of the scorer, and keep
    the statistics' own cadence."""
    start = 2
    model, cameras = planted_floater_model("concrete", start=start, every=3, enhanced_every=every)
    model.train()
    refreshed, beta_weights = [], []
    refresh = model.refresh_paup_statistics
    monkeypatch.setattr(model, "refresh_paup_statistics", lambda camera: (refreshed.append(model.paup.step),
                                                                          refresh(camera)))
    regularizer = model.medium.regularizer
    monkeypatch.setattr(model.medium, "regularizer", lambda points, weights=None: (beta_weights.append(weights),
                                                                                   regularizer(points, weights))[1])
    batch = {"camera": cameras[1], "image": torch.zeros(30, 40, 3)}
    full_keys = None
    for step in range(start - 1, start + 6):
        model.paup.set_step(step)
        outputs = model.get_outputs(cameras[1])
        losses = model.get_loss_dict(outputs, batch, step)
        if step < start:  # no branch yet: L_beta unweighted (PUS = 1)
            assert "pus" not in outputs and beta_weights[-1] is None
            continue
        torch.testing.assert_close(beta_weights[-1], model.paup.pus().detach(), rtol=0, atol=0)
        enhanced = (step - start) % every == 0
        assert ("uri_enhanced" in outputs, "floater_probability" in outputs, "paup_loss" in losses) == (enhanced,) * 3
        full_keys = set(outputs) if enhanced else full_keys
        if not enhanced:
            assert set(outputs) == full_keys - {"uri_enhanced", "uri_enhanced_l1", "floater_probability"}
            model.zero_grad(set_to_none=True)
            sum(losses.values()).backward()
            assert all(p.grad is None for p in model.paup.scorer.parameters())
    assert refreshed == [start, start + 3]


def test_uncertainty_weighted_depth_against_a_per_gaussian_sum():
    """With the weights (1 - U_i) the depth is sum w_i d_i z_i / sum w_i d_i: checked by splitting the render into
    one image per Gaussian (the blending weights do not depend on the depth weights)."""
    model, cameras = planted_floater_model()
    camera = cameras[0]
    weights = torch.rand(model.num_gaussians, generator=torch.Generator().manual_seed(0))
    with torch.no_grad():
        got = model.render(camera, depth_weights=weights)
        means = model.gaussians.means
        z = means @ camera.viewmat[2, :3] + camera.viewmat[2, 3]
        plain = model.render(camera)
        num = model.render(camera, depth_weights=weights * 0 + 1)  # weights of one: the plain depth
    torch.testing.assert_close(num["depth"], plain["depth"], rtol=1e-5, atol=1e-6)
    # brute force: composite (d_i z_i) and d_i as features with the reference rasterizer in float64
    from uw3dgs.render import Splats
    from uw3dgs.render.reference import rasterize_reference

    m, s, q, o = (t.double() for t in model.gaussians.activated())
    feats = torch.stack([weights.double(), weights.double() * z.double()], dim=-1)
    camera64 = Camera(camera.viewmat.double(), camera.K.double(), camera.width, camera.height)
    ref = rasterize_reference(Splats(m, q, s, o, feats), camera64, model.config.raster)
    covered = ref.render[..., 0] > COVERAGE_EPS
    expected = ref.render[..., 1][covered] / ref.render[..., 0][covered]
    torch.testing.assert_close(got["depth"][covered].double(), expected, rtol=1e-4, atol=1e-5)


# -- whole runs --

def test_no_paup_equals_the_branch_never_starting(make_config):
    """`uw3dgs-no-paup` is `uw3dgs` without the branch: the same seed and steps give the same parameters as a
    `uw3dgs` run whose PAUP starts after the last step (densification events and all)."""
    never = train(tiny_uw3dgs(make_config, "uw3dgs", steps=25, paup_start=1000))
    ablation = train(tiny_uw3dgs(make_config, "uw3dgs-no-paup", steps=25, paup_start=1000))
    assert ablation.model.paup is None
    a, b = never.model.state_dict(), ablation.model.state_dict()
    for key in b:
        assert torch.equal(a[key], b[key]), key
    assert set(a) - set(b) == {k for k in a if k.startswith("paup.")}


def test_paup_trains_prunes_on_schedule_and_resumes(make_config, monkeypatch):
    config = tiny_uw3dgs(make_config, "uw3dgs", steps=30, paup_start=5)
    full = train(dataclasses.replace(config, timestamp="full"))
    reference = {key: value.clone() for key, value in full.model.state_dict().items()}
    assert bool(full.model.paup.measured.any())
    assert len(full.model.paup.uncertainty) == full.model.num_gaussians
    summary = full.eval_all(30)
    assert 0.0 <= summary["pruned_share"] <= 1.0 and "floater_ratio" in summary
    losses, metrics = full.train_step(31)
    assert "paup_loss" in losses and "paup/w_u" in metrics

    train_until_killed(dataclasses.replace(config, timestamp="killed"), monkeypatch, step=23)
    resumed = Trainer(dataclasses.replace(config, timestamp="killed", resume=True))
    resumed.setup()
    resumed.train()
    resumed_state = resumed.model.state_dict()
    assert reference.keys() == resumed_state.keys()
    for key, value in reference.items():
        torch.testing.assert_close(value, resumed_state[key], rtol=1e-5, atol=1e-6, msg=key)


@pytest.mark.parametrize("flag, value, message", [
    ("--model.paup.prune-quantile", "1.5", "must be a finite number > 0 and < 1, got 1.5"),
    ("--model.paup.num-views", "1", "must be a whole number >= 2, got 1"),
    ("--model.paup.mask-temperature", "0", "must be a finite number > 0, got 0.0"),
    ("--model.paup.enhanced-every", "0", "must be a whole number >= 1, got 0"),
])
def test_a_bad_paup_option_is_one_line_naming_it(tmp_path, capsys, flag, value, message):
    from uw3dgs.cli.train import entrypoint as uw_train

    with pytest.raises(SystemExit) as exc:
        uw_train(["uw3dgs", "--output-dir", str(tmp_path / "out"), flag, value])
    out = capsys.readouterr().out
    assert exc.value.code == 2 and f"error: {flag} {message}" in out, out
    assert "Traceback" not in out and not (tmp_path / "out").exists()


def test_an_unknown_mask_names_the_choices(tmp_path, capsys):
    from uw3dgs.cli.train import entrypoint as uw_train

    with pytest.raises(SystemExit) as exc:
        uw_train(["uw3dgs", "--output-dir", str(tmp_path / "out"), "--model.paup.mask", "hard"])
    captured = capsys.readouterr()
    out = " ".join((captured.out + captured.err).replace("│", " ").split())
    assert exc.value.code == 2 and "'--model.paup.mask'" in out and "('concrete', 'expected')" in out, out
    assert not (tmp_path / "out").exists()
