"""3DGS adaptive density control: which Gaussians are cloned, split, pruned, and that Adam follows."""

from __future__ import annotations

import math

import torch

from uw3dgs.engine.optimizers import Optimizers, ParamGroupConfig
from uw3dgs.fields.gaussians import PARAM_NAMES, GaussianField, GaussianFieldConfig
from uw3dgs.strategy import DefaultStrategy, DensificationConfig


def make(extent: float = 1.0, **config):
    points = torch.tensor([[0.0, 0, 0], [1.0, 0, 0], [0, 1.0, 0], [0, 0, 1.0]])
    field = GaussianField(GaussianFieldConfig(), points, torch.full((4, 3), 0.5))
    with torch.no_grad():
        field.scales[:] = math.log(0.005)
        field.scales[1] = math.log(0.5)  # large: split rather than clone
        field.opacities[:] = 2.0
        field.opacities[2] = -8.0  # sigmoid ~ 3e-4 < min_opacity
    optimizers = Optimizers({n: ParamGroupConfig(1e-3) for n in PARAM_NAMES}, field.param_groups(), extent, 100)
    # one real Adam step so the moments exist and must be carried along
    sum((getattr(field, n) ** 2).sum() for n in PARAM_NAMES).backward()
    optimizers.step()
    strategy = DefaultStrategy(DensificationConfig(**config), extent, 30000)
    return field, optimizers, strategy, strategy.initialize_state(field)


def test_clone_split_prune_and_adam_state_follow():
    field, optimizers, strategy, state = make()
    state["grad_accum"][:] = torch.tensor([1.0, 1.0, 0.0, 0.0])
    state["visible_count"][:] = 1
    before = {n: getattr(field, n).detach().clone() for n in PARAM_NAMES}
    strategy.densify_and_prune(field, optimizers, state, step=500)
    # 4 + 1 clone + 2 split children - 1 split parent - 1 transparent
    assert field.num_gaussians == 5
    torch.testing.assert_close(field.means[:2], before["means"][[0, 3]])  # survivors keep their order
    torch.testing.assert_close(field.means[2], before["means"][0])  # the clone sits on its original
    children = field.scales[3:].exp()
    torch.testing.assert_close(children, before["scales"][1].exp().expand(2, 3) / 1.6)
    for name in PARAM_NAMES:
        param = getattr(field, name)
        adam = optimizers.optimizers[name].state[param]
        assert adam["exp_avg"].shape == param.shape, name
        assert optimizers.optimizers[name].param_groups[0]["params"][0] is param
    assert state["grad_accum"].shape == (5,) and float(state["grad_accum"].sum()) == 0.0
    # the (fused) Adam steps on with the carried moments
    sum((getattr(field, n) ** 2).sum() for n in PARAM_NAMES).backward()
    optimizers.step()
    assert not torch.equal(field.means[:2], before["means"][[0, 3]])


def test_adam_is_fused_gives_the_loops_update_and_stays_fused_when_loading_an_unfused_state():
    def second_step(fused: bool):
        field, optimizers, _, _ = make()  # built fused, one step taken
        for opt in optimizers.optimizers.values():
            assert all(group["fused"] for group in opt.param_groups)
            for group in opt.param_groups:
                group["fused"] = fused
        sum((getattr(field, n) ** 2).sum() for n in PARAM_NAMES).backward()
        optimizers.step()
        return field, optimizers

    fused_field, _ = second_step(True)
    loop_field, loop_optimizers = second_step(False)
    for name in PARAM_NAMES:
        torch.testing.assert_close(getattr(fused_field, name), getattr(loop_field, name), rtol=1e-6, atol=1e-7)
    # a checkpoint of the loop (runs from before the switch) loads into an Adam that stays fused and steps on
    field, optimizers, _, _ = make()
    optimizers.load_state_dict(loop_optimizers.state_dict())
    for opt in optimizers.optimizers.values():
        assert all(group["fused"] for group in opt.param_groups)
    sum((getattr(field, n) ** 2).sum() for n in PARAM_NAMES).backward()
    optimizers.step()


def test_opacity_reset_happens_on_schedule_and_clears_moments():
    """gsplat 1.5.3's strategy never resets (a bitwise & on a bool); ours must, at every multiple."""
    field, optimizers, strategy, state = make(reset_opacity_every=3000, refine_every=10**9)
    strategy.step_post_optimizer(field, optimizers, state, 2999)
    assert torch.sigmoid(field.opacities).max() > 0.5
    strategy.step_post_optimizer(field, optimizers, state, 3000)
    assert torch.sigmoid(field.opacities).max() <= 0.01 + 1e-6
    state = optimizers.optimizers["opacities"].state[field.opacities]
    assert float(state["exp_avg"].abs().sum()) == 0.0


def test_no_reset_after_densification_stops():
    field, optimizers, strategy, state = make(reset_opacity_every=3000, refine_stop=5000, refine_every=10**9)
    strategy.step_post_optimizer(field, optimizers, state, 6000)
    assert torch.sigmoid(field.opacities).max() > 0.5


def test_refine_stop_is_half_the_run_or_less():
    stops = {(stop, steps): DefaultStrategy(DensificationConfig(refine_stop=stop), 1.0, steps).refine_stop
             for stop in (None, 15000) for steps in (6000, 30000, 40000)}
    assert stops == {(None, 6000): 3000, (None, 30000): 15000, (None, 40000): 20000,
                     (15000, 6000): 3000, (15000, 30000): 15000, (15000, 40000): 15000}


def test_statistics_are_ndc_gradient_norms_and_largest_screen_radii():
    """step_post_backward: |d loss / d ndc| summed per visible Gaussian, visible views counted, and the largest
    screen radius kept (a share of the image's larger side), all on the Gaussians' device; nothing after the stop."""
    field, _, strategy, state = make(refine_stop=100)
    means2d = torch.zeros(4, 2, requires_grad=True)
    (means2d * torch.tensor([[1.0, 2.0], [3.0, 4.0], [5.0, 6.0], [7.0, 8.0]])).sum().backward()
    means2d.grad[1] = float("nan")  # whatever an invisible Gaussian's gradient holds, it is not read
    radii = torch.tensor([2, 0, 8, 4])
    for radius_scale in (1, 2):
        strategy.step_post_backward(state, 10, means2d, radii * radius_scale, (40, 20))
    expected = torch.tensor([math.hypot(20, 20), 0.0, math.hypot(100, 60), math.hypot(140, 80)]) * 2
    torch.testing.assert_close(state["grad_accum"], expected)
    assert state["visible_count"].tolist() == [2, 0, 2, 2]
    torch.testing.assert_close(state["max_radii"], torch.tensor([4.0, 0.0, 16.0, 8.0]) / 40)
    assert all(v.device == field.means.device for v in state.values())
    strategy.step_post_backward(state, 101, means2d, radii, (40, 20))  # after refine_stop: no statistics
    assert state["visible_count"].tolist() == [2, 0, 2, 2]


def test_methods_carry_their_schedules():
    from uw3dgs.registry import METHODS

    schedules = {name: (spec.config.max_num_iterations, spec.config.model.densification.refine_stop)
                 for name, spec in METHODS.items() if hasattr(spec.config.model, "densification")}
    assert schedules["3dgs"] == (30000, None)  # 3DGS: densify until 15,000 = half of 30,000
    for name in ("uw3dgs", "uw3dgs-no-medium", "uw3dgs-no-lbeta", "uw3dgs-no-lz", "uw3dgs-paper",
                 "uw3dgs-paper-no-paup", "uw3dgs-paper-no-medium", "uw3dgs-paper-no-lbeta", "uw3dgs-paper-no-lz"):
        assert schedules[name] == (40000, 15000), name  # DESIGN: until 15,000 of 40,000
