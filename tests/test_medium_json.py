"""medium.json: a grid medium that is one value everywhere is written as one value per channel, a varying one as
its grid."""

from __future__ import annotations

import pytest
import torch

from uw3dgs.fields.medium import MediumGrid, MediumGridConfig


def test_a_constant_grid_is_one_value_and_a_varying_one_a_grid():
    generator = torch.Generator().manual_seed(0)
    medium = MediumGrid.around(MediumGridConfig(), torch.rand(200, 3, generator=generator), torch.zeros(2, 3))
    medium.set_homogeneous(torch.tensor([0.1, 0.2, 0.3]), torch.tensor([0.05, 0.06, 0.07]), torch.full((3,), 0.4))
    flat = medium.summary((0.0, 0.0, 0.0), 1.0, samples=4)
    assert flat["kind"] == "homogeneous"
    assert flat["beta_d"] == pytest.approx([0.1, 0.2, 0.3], rel=1e-4)
    assert flat["beta_b"] == pytest.approx([0.05, 0.06, 0.07], rel=1e-4)
    with torch.no_grad():
        for parameter in medium.beta_d.parameters():
            parameter.add_(0.05 * torch.randn(parameter.shape, generator=generator))
    varying = medium.summary((0.0, 0.0, 0.0), 1.0, samples=4)
    assert varying["kind"] == "grid" and len(varying["beta_d"]) == 4
