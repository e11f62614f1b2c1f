"""PAUP as the paper writes it, each a knob of `uw3dgs` that `uw3dgs-paper` sets: pruning at the 0.95-quantile of m
every step through the whole run with no floor on m, and the UWI formed from I_UR^Enh with L_PAPSL reaching the
Gaussians."""

from __future__ import annotations

import pytest
import torch
from test_paup import planted_floater_model

from uw3dgs.methods.uw3dgs.paup import PAUP, PAUPConfig
from uw3dgs.strategy import DefaultStrategy, DensificationConfig

STEPS = 1000


def pruning_steps(config: PAUPConfig) -> list[int]:
    strategy = DefaultStrategy(DensificationConfig(refine_start=100, refine_every=100, refine_stop=500), 1.0, STEPS)
    paup = PAUP(config, num_gaussians=4)
    return [step for step in range(STEPS + 1) if paup.prunes_at(step, strategy)]


def test_the_paper_schedule_prunes_every_n_steps_from_start_to_the_end():
    assert pruning_steps(PAUPConfig(start=40, prune_schedule="every", prune_every=30)) == list(range(40, STEPS + 1, 30))
    assert pruning_steps(PAUPConfig(start=40, prune_schedule="every")) == list(range(40, STEPS + 1))
    # this project's reading: at densification events only, or on their cadence after them with the late knob
    assert pruning_steps(PAUPConfig()) == [100, 200, 300, 400, 500]
    assert pruning_steps(PAUPConfig(prune_after_densification=True)) == list(range(100, STEPS + 1, 100))


@pytest.mark.parametrize("floor, pruned", [(0.5, []), (0.0, [95, 96, 97, 98, 99])])
def test_without_the_floor_the_top_share_of_m_goes_however_low_m_is(floor, pruned):
    paup = PAUP(PAUPConfig(normalize_scores=False, prune_min_probability=floor), num_gaussians=100)
    paup.update(torch.zeros(100), torch.linspace(0.0, 2.0, 100), torch.ones(100, dtype=torch.bool))
    m = paup.scores()[1].detach()
    assert float(m.max()) < 0.5 and bool((m.diff() > 0).all())  # all below the floor, ranked as P
    assert paup.candidates().nonzero().squeeze(1).tolist() == pruned


@pytest.mark.parametrize("paper", [False, True])
def test_the_paper_wiring_forms_the_uwi_from_i_ur_enh_and_papsl_reaches_the_gaussians(paper):
    model, cameras = planted_floater_model(uwi_from_enhanced=paper)
    model.train()
    model.paup.set_step(0)
    outputs = model.get_outputs(cameras[0])
    scorer = model.paup.scorer
    # the UWI depends on the keep mask (so on the scorer) exactly when it is formed from I_UR^Enh
    (to_mask,) = torch.autograd.grad(outputs["rgb"].sum(), scorer.raw_w_p, retain_graph=True, allow_unused=True)
    assert (to_mask is not None and float(to_mask.abs()) > 0) == paper
    losses = model.get_loss_dict(outputs, {"camera": cameras[0], "image": torch.zeros(30, 40, 3)}, step=0)
    losses["paup_loss"].backward()
    grad = model.gaussians.opacities.grad
    assert (grad is not None and float(grad.abs().sum()) > 0) == paper
    assert float(scorer.raw_w_p.grad.abs()) > 0  # the scorer learns either way
