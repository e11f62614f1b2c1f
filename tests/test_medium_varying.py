"""The medium that varies in space: the multi-view field fit (fields/medium_varying.py), its factor field against
brute-force references, and the VM grid started from it (fields/medium.py, `MediumGrid.set_factor`)."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from uw3dgs.fields.medium import MediumGridConfig
from uw3dgs.fields.medium_multiview import MultiviewConfig, fit_multiview
from uw3dgs.fields.medium_varying import FactorField, _varying_model, varying_estimate
from uw3dgs.options import OptionError

BETA_D, BETA_B, B_INF = (0.30, 0.12, 0.08), (0.24, 0.20, 0.16), (0.20, 0.30, 0.40)


def seabed(num_points: int = 240, seed: int = 0) -> torch.Tensor:
    """[P, 3] points on the plane z = 0 over x in [-5, 5], y in [-2, 2]."""
    g = torch.Generator().manual_seed(seed)
    xy = torch.rand(num_points, 2, generator=g, dtype=torch.float64) * torch.tensor([10.0, 4.0]) - torch.tensor(
        [5.0, 2.0])
    return torch.cat([xy, torch.zeros(num_points, 1, dtype=torch.float64)], dim=-1)


def two_pass_survey(factor, num_points: int = 240, noise: float = 0.004, seed: int = 0):
    """Each seabed point seen from 3 cameras 2 units up and 3 cameras 4 units up (horizontal offsets up to 1.5),
    through a medium whose betas are BETA x factor(x) (world points [N, 3] -> [N], linear along a ray so its
    mean along the ray is its value at the ray's middle). Returns (point ids [M], colours [M, 3], ranges [M], ray
    starts [M, 3], ray ends [M, 3], positions [P, 3])."""
    g = torch.Generator().manual_seed(seed + 1)
    positions = seabed(num_points, seed)
    point = torch.arange(num_points).repeat_interleave(6)
    offsets = (torch.rand(len(point), 2, generator=g, dtype=torch.float64) - 0.5) * 3.0
    heights = torch.tensor([2.0, 2.0, 2.0, 4.0, 4.0, 4.0], dtype=torch.float64).repeat(num_points)
    ends = positions[point]
    starts = ends + torch.cat([offsets, heights[:, None]], dim=-1)
    z = (ends - starts).norm(dim=-1)
    m = factor((starts + ends) / 2)[:, None]
    bd, bb, b = (torch.tensor(v, dtype=torch.float64) for v in (BETA_D, BETA_B, B_INF))
    clean = 0.1 + 0.7 * torch.rand(num_points, 3, generator=g, dtype=torch.float64)
    color = clean[point] * torch.exp(-bd * m * z[:, None]) + b * (1 - torch.exp(-bb * m * z[:, None]))
    color = color + noise * torch.randn(color.shape, generator=g, dtype=torch.float64)
    return point, color, z, starts, ends, positions


def ramp(x: torch.Tensor) -> torch.Tensor:
    """A factor from 0.6 to 1.4 across x in [-5, 5]: the water thickens along the survey."""
    return 1.0 + 0.08 * x[:, 0]


def test_the_factor_field_interpolates_its_nodes_and_its_ray_weights_are_the_mean_along_the_ray():
    positions = seabed()
    field = FactorField.around(positions, 4)
    values = torch.rand(4, 4, generator=torch.Generator().manual_seed(3), dtype=torch.float64) + 0.5
    field = field.with_values(values)
    weights = field.weights(positions)
    torch.testing.assert_close(weights.sum(-1), torch.ones(len(positions), dtype=torch.float64))
    # at a node the field is the node's value; outside the nodes it is the border's (clamped)
    node = field.center + field.ticks[0, 1] * field.axes[0] + field.ticks[1, 2] * field.axes[1]
    torch.testing.assert_close(field(node[None]), values[1, 2].reshape(1))
    far = field.center + 100 * field.axes[0] + field.ticks[1, 0] * field.axes[1]
    torch.testing.assert_close(field(far[None]), values[-1, 0].reshape(1))
    # the mean along a segment against a brute-force mean over 4,000 points of it (float64)
    starts, ends = positions[:20] + torch.tensor([1.0, -0.5, 3.0], dtype=torch.float64), positions[:20]
    brute = torch.stack([field(s + (e - s) * torch.linspace(0, 1, 4000, dtype=torch.float64)[:, None]).mean()
                         for s, e in zip(starts, ends, strict=True)])
    torch.testing.assert_close(field.ray_weights(starts, ends, 64) @ values.reshape(-1), brute, atol=2e-3, rtol=0)


def test_the_field_models_derivatives_match_autograd():
    g = torch.Generator().manual_seed(0)
    theta = -1 + 0.3 * torch.randn(3, 3, generator=g, dtype=torch.float64)
    u = 0.2 * torch.randn(9, generator=g, dtype=torch.float64)
    clean = torch.rand(3, 10, generator=g, dtype=torch.float64)
    point = torch.randint(10, (50,), generator=g)
    z = 1 + 5 * torch.rand(50, generator=g, dtype=torch.float64)
    phi = torch.rand(50, 9, generator=g, dtype=torch.float64)
    phi = phi / phi.sum(-1, keepdim=True)
    _, d_clean, d_global = _varying_model(theta, u, clean, point, z, phi)

    def predict(flat: torch.Tensor) -> torch.Tensor:
        return _varying_model(flat[:9].view(3, 3), flat[9:], clean, point, z, phi, derivatives=False)[0]

    torch.testing.assert_close(d_global, torch.autograd.functional.jacobian(predict, torch.cat([theta.flatten(), u])))
    by_clean = torch.autograd.functional.jacobian(
        lambda c: _varying_model(theta, u, c, point, z, phi, derivatives=False)[0], clean)
    rows = torch.arange(50)
    torch.testing.assert_close(d_clean, torch.stack([by_clean[c, rows, c, point] for c in range(3)]))


def _field_estimate(factor, **config):
    point, color, z, starts, ends, positions = two_pass_survey(factor)
    config = MultiviewConfig(field_nodes=4, field_resamples=3, **config)
    start = fit_multiview(point, color, z, config=config)
    return varying_estimate(point, color, z, starts, ends, torch.ones_like(z), start, positions, config=config), \
        positions


def test_the_field_fit_recovers_water_that_thickens_across_a_two_pass_survey():
    estimate, positions = _field_estimate(ramp)
    fit = estimate.fit
    factor = fit.factor(positions)
    truth = ramp(positions)
    assert float(np.corrcoef(factor.numpy(), truth.numpy())[0, 1]) > 0.99
    for learned, reference in ((fit.beta_d, BETA_D), (fit.beta_b, BETA_B)):
        field = learned.double() * factor[:, None]
        true_field = torch.tensor(reference, dtype=torch.float64) * truth[:, None]
        assert float(((field - true_field).abs() / true_field).mean()) < 0.05
    torch.testing.assert_close(fit.b_inf.double(), torch.tensor(B_INF, dtype=torch.float64), atol=0.01, rtol=0)
    assert estimate.all_betas_identified
    assert 1.25 < estimate.factor_range[1] / estimate.factor_range[0] < 2.5  # the truth's 5-95%: 0.64-1.36 (2.1x)


def test_the_field_fit_keeps_homogeneous_water_flat():
    """Bound: the fitted factor within 3% of 1 over every point where the water is the same everywhere."""
    estimate, positions = _field_estimate(lambda x: torch.ones(len(x), dtype=torch.float64))
    factor = estimate.fit.factor(positions)
    assert float((factor - 1).abs().max()) < 0.03


def test_a_grid_started_from_a_factor_holds_it_and_pulls_toward_it():
    positions = seabed(600).float()
    cameras = torch.tensor([[-4.0, 0.0, 3.0], [4.0, 0.0, 3.0]])
    config = MediumGridConfig(resolution=16, components=4, distill_steps=150, distill_lr=0.05)
    medium = config.setup(points=positions, camera_centers=cameras, kernels="torch")
    medium.set_homogeneous(torch.tensor(BETA_D), torch.tensor(BETA_B), torch.tensor(B_INF))
    medium.set_prior(torch.tensor(BETA_D), torch.tensor(BETA_B))
    medium.set_factor(lambda x: ramp(x.double()).float(), positions)
    with torch.no_grad():
        beta_d, beta_b = medium.betas(positions)
        truth = ramp(positions.double()).float()[:, None]
        assert float(((beta_d - torch.tensor(BETA_D) * truth).abs() / (torch.tensor(BETA_D) * truth)).mean()) < 0.03
        torch.testing.assert_close(medium.prior_factor_at(positions), truth, atol=0.02, rtol=0)
        # L_beta pulls toward the varying field: near 0 at the start, far from 0 for the flat field it replaced
        at_start = float(medium.regularizer(positions) - medium.factor_penalty())
        medium.set_homogeneous(torch.tensor(BETA_D), torch.tensor(BETA_B), torch.tensor(B_INF))
        flat = float(medium.regularizer(positions) - medium.factor_penalty())
    assert at_start < 0.05 * flat


@pytest.mark.parametrize("start", ["zero-basis", "constant-factors"])
def test_a_grid_started_from_a_factor_gets_image_gradients_on_its_factors(start):
    positions = seabed(300).float()
    config = MediumGridConfig(resolution=8, components=2, distill_steps=30, flat_start=start)
    medium = config.setup(points=positions, camera_centers=torch.tensor([[0.0, 0.0, 3.0]]), kernels="torch")
    medium.set_factor(lambda x: ramp(x.double()).float(), positions)
    beta_d, beta_b = medium.betas(positions)
    (beta_d.sum() + beta_b.sum()).backward()  # stands in for any image loss through the betas
    for field in (medium.beta_d, medium.beta_b):
        assert float(field.planes.grad.abs().sum()) > 0 and float(field.lines.grad.abs().sum()) > 0


def test_a_field_of_one_node_is_refused_with_the_option_named():
    with pytest.raises(OptionError, match="field_nodes"):
        MultiviewConfig(field_nodes=1)
