"""The run uw-process-data suggests: the downscale factor and steps sized to a time budget on the CPU (from the
step-cost model), 3DGS's own size on a GPU, and the command line printed."""

from __future__ import annotations

import pytest

from uw3dgs.engine.run_size import MIN_SIDE, STEP_QUANTUM, StepCost, size_run, suggestion

COST = StepCost(base_s=0.1, per_megapixel_s=1.0)


def test_cpu_takes_the_finest_factor_that_fits_the_budget():
    size = size_run(1600, 900, "cpu", budget_s=1800, cpu_steps=6000, cost=COST)
    assert (size.factor, size.steps, size.width, size.height) == (4, 6000, 400, 225)
    assert size.seconds == pytest.approx(6000 * (0.1 + 400 * 225 / 1e6))
    assert size.seconds <= 1800 < 6000 * COST.seconds_per_step(800, 450)  # factor 2 would not fit


def test_cpu_shortens_the_run_when_no_factor_fits():
    size = size_run(1600, 900, "cpu", budget_s=300, cpu_steps=6000, cost=COST)
    assert max(size.width, size.height) >= MIN_SIDE and max(size.width // 2, size.height // 2) < MIN_SIDE
    assert size.steps % STEP_QUANTUM == 0 and STEP_QUANTUM <= size.steps < 6000 and size.seconds <= 300


def test_gpu_uses_3dgs_size_without_a_time():
    size = size_run(4000, 3000, "cuda", budget_s=1800, cpu_steps=6000, cost=COST)
    assert (size.factor, size.steps, size.seconds) == (4, 30000, None)
    assert "no time estimate" in suggestion("uw3dgs", "data/x", size, "cuda")


def test_the_suggestion_is_a_command_line():
    size = size_run(1600, 900, "cpu", budget_s=1800, cpu_steps=6000, cost=COST)
    text = suggestion("uw3dgs", "data/fox", size, "cpu")
    assert text.startswith("Train on it with: uw-train uw3dgs --data data/fox --downscale-factor 4 "
                           "--max-num-iterations 6000\n")
    assert f"about {size.seconds / 60:.0f} minutes" in text
