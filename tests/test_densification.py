"""3DGS adaptive density control: which Gaussians are cloned, split, pruned, and that Adam follows."""

from __future__ import annotations

import math

import torch

from uw3dgs.engine.optimizers import Optimizers, ParamGroupConfig
from uw3dgs.fields.densification import DensificationConfig, Densifier
from uw3dgs.fields.gaussians import PARAM_NAMES, GaussianField, GaussianFieldConfig


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
    densifier = Densifier(DensificationConfig(**config), field, optimizers, extent, 30000)
    return field, optimizers, densifier


def test_clone_split_prune_and_adam_state_follow():
    field, optimizers, densifier = make()
    densifier.grad_accum[:] = torch.tensor([1.0, 1.0, 0.0, 0.0])
    densifier.visible_count[:] = 1
    before = {n: getattr(field, n).detach().clone() for n in PARAM_NAMES}
    densifier.densify_and_prune(step=500)
    # 4 + 1 clone + 2 split children - 1 split parent - 1 transparent
    assert field.num_gaussians == 5
    torch.testing.assert_close(field.means[:2], before["means"][[0, 3]])  # survivors keep their order
    torch.testing.assert_close(field.means[2], before["means"][0])  # the clone sits on its original
    children = field.scales[3:].exp()
    torch.testing.assert_close(children, before["scales"][1].exp().expand(2, 3) / 1.6)
    for name in PARAM_NAMES:
        param = getattr(field, name)
        state = optimizers.optimizers[name].state[param]
        assert state["exp_avg"].shape == param.shape, name
        assert optimizers.optimizers[name].param_groups[0]["params"][0] is param
    assert densifier.grad_accum.shape == (5,) and float(densifier.grad_accum.sum()) == 0.0
    # the (fused) Adam steps on with the carried moments
    sum((getattr(field, n) ** 2).sum() for n in PARAM_NAMES).backward()
    optimizers.step()
    assert not torch.equal(field.means[:2], before["means"][[0, 3]])


def test_adam_is_fused_gives_the_loops_update_and_stays_fused_when_loading_an_unfused_state():
    def second_step(fused: bool):
        field, optimizers, _ = make()  # built fused, one step taken
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
    field, optimizers, _ = make()
    optimizers.load_state_dict(loop_optimizers.state_dict())
    for opt in optimizers.optimizers.values():
        assert all(group["fused"] for group in opt.param_groups)
    sum((getattr(field, n) ** 2).sum() for n in PARAM_NAMES).backward()
    optimizers.step()


def test_opacity_reset_happens_on_schedule_and_clears_moments():
    """gsplat 1.5.3's strategy never resets (a bitwise & on a bool); ours must, at every multiple."""
    field, optimizers, densifier = make(reset_opacity_every=3000, refine_every=10**9)
    densifier.after_step(2999, {})
    assert torch.sigmoid(field.opacities).max() > 0.5
    densifier.after_step(3000, {})
    assert torch.sigmoid(field.opacities).max() <= 0.01 + 1e-6
    state = optimizers.optimizers["opacities"].state[field.opacities]
    assert float(state["exp_avg"].abs().sum()) == 0.0


def test_no_reset_after_densification_stops():
    field, _, densifier = make(reset_opacity_every=3000, refine_stop=5000, refine_every=10**9)
    densifier.after_step(6000, {})
    assert torch.sigmoid(field.opacities).max() > 0.5


def test_refine_stop_is_half_the_run_or_less():
    field, optimizers, _ = make()
    stops = {(stop, steps): Densifier(DensificationConfig(refine_stop=stop), field, optimizers, 1.0, steps).refine_stop
             for stop in (None, 15000) for steps in (6000, 30000, 40000)}
    assert stops == {(None, 6000): 3000, (None, 30000): 15000, (None, 40000): 20000,
                     (15000, 6000): 3000, (15000, 30000): 15000, (15000, 40000): 15000}


def test_methods_carry_their_schedules():
    from uw3dgs.registry import METHODS

    schedules = {name: (spec.config.max_num_iterations, spec.config.model.densification.refine_stop)
                 for name, spec in METHODS.items()}
    assert schedules["3dgs"] == (30000, None)  # 3DGS: densify until 15,000 = half of 30,000
    for name in ("uw3dgs", "uw3dgs-no-medium", "uw3dgs-no-lbeta", "uw3dgs-no-lz"):
        assert schedules[name] == (40000, 15000), name  # DESIGN: until 15,000 of 40,000
