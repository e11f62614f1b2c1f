"""The compiled VM products (uw3dgs/kernels/vm_field.py, `vm_products`) that the TensoRF field reads with, against
grid_sample (fields/tensorf.py, `vm_products`): values and gradients, per-mode ranks, box-shaped grids, points on
cell borders and box edges, and a model's training step under either `--model.kernels`."""

from __future__ import annotations

import dataclasses

import pytest
import torch

from uw3dgs.datamanagers.synthetic import SyntheticDataManagerConfig
from uw3dgs.datamanagers.synthetic.config import SyntheticSceneConfig
from uw3dgs.fields.tensorf import COMPILED_AXES, TensoRFFieldConfig, vm_products
from uw3dgs.kernels import vm_field
from uw3dgs.registry import METHODS

RANKS = (18, 3, 1)
"""Per-mode ranks: one above the kernel's block of 16 components (two blocks), and a rank of 1."""
RESOLUTION = (7, 4, 9)
"""A box-shaped grid (X, Y, Z vertices)."""


def factors(dtype: torch.dtype, ranks=RANKS, resolution=RESOLUTION, seed=0):
    """Random planes [1, R_m, G_b, G_a] and lines [1, R_m, G_c, 1] in TensoRF's layout, as its field has them."""
    field = TensoRFFieldConfig(density_components=ranks, init_scale=1.0).setup(
        lo=-torch.ones(3), hi=torch.ones(3), resolution=resolution, kernels="torch")
    g = torch.Generator().manual_seed(seed)
    planes = [torch.randn(p.shape, generator=g, dtype=dtype).requires_grad_() for p in field.density_planes]
    lines = [torch.randn(q.shape, generator=g, dtype=dtype).requires_grad_() for q in field.density_lines]
    return planes, lines


def points(dtype: torch.dtype, n: int = 3000, resolution=RESOLUTION, seed=1) -> torch.Tensor:
    """Random points in [-1, 1]^3, then every grid vertex along each axis (cell borders, the box's faces at +-1), the
    box's corners, and a few just outside (read as zero beyond the grid, grid_sample's padding)."""
    g = torch.Generator().manual_seed(seed)
    u = torch.rand(n, 3, generator=g, dtype=dtype) * 2 - 1
    k = torch.arange(n)
    for axis, size in enumerate(resolution):  # every third point on a vertex of some axis
        on = k % 3 == axis
        u[on, axis] = (-1 + 2 * (k[on] % size).to(dtype) / (size - 1))
    corners = torch.tensor([[x, y, z] for x in (-1, 1) for y in (-1, 1) for z in (-1, 1)], dtype=dtype)
    outside = torch.tensor([[1.05, 0.0, 0.0], [0.3, -1.2, 0.5], [0.1, 0.2, 1.0 + 1e-3]], dtype=dtype)
    return torch.cat([u, corners, outside])


def compiled(planes, lines, u, summed):
    return vm_field.vm_products(u, [p[0] for p in planes], [q[0, :, :, 0] for q in lines], COMPILED_AXES, summed)


def reference(planes, lines, u, summed):
    products = vm_products(planes, lines, u)
    return sum(p.sum(dim=-1) for p in products) if summed else torch.cat(products, dim=-1)


def values_and_grads(read, planes, lines, u, summed):
    out = read(planes, lines, u, summed)
    weights = torch.randn(out.shape, generator=torch.Generator().manual_seed(2), dtype=out.dtype)
    grads = torch.autograd.grad((out * weights).sum(), [*planes, *lines])
    return [out.detach(), *grads]


@pytest.mark.parametrize(("dtype", "tolerance"), [(torch.float64, 1e-12), (torch.float32, 1e-5)])
@pytest.mark.parametrize("summed", [False, True])
def test_compiled_products_match_grid_sample(dtype, tolerance, summed):
    """Values and the planes' and lines' gradients, relative to each tensor's largest value; concatenated
    (appearance) and summed (density)."""
    planes, lines = factors(dtype)
    u = points(dtype)
    ours = values_and_grads(compiled, planes, lines, u, summed)
    theirs = values_and_grads(reference, planes, lines, u, summed)
    assert ours[0].shape == theirs[0].shape == ((len(u),) if summed else (len(u), sum(RANKS)))
    for a, b in zip(ours, theirs, strict=True):
        assert a.shape == b.shape and float((a - b).abs().max() / b.abs().max()) < tolerance
    assert float(ours[0][-3:].abs().max()) < float(ours[0][:-3].abs().max())  # outside: the padding's zeros count


def test_compiled_products_gradcheck():
    planes, lines = factors(torch.float64, ranks=(2, 1, 3), resolution=(3, 4, 2))
    u = points(torch.float64, n=5, resolution=(3, 4, 2))[:9]

    def fn(*values):
        return compiled(values[:3], values[3:], u, False)

    assert torch.autograd.gradcheck(fn, (*planes, *lines))


def test_compiled_products_are_bitwise_deterministic_across_threads():
    planes, lines = factors(torch.float32)
    u = points(torch.float32, n=20_000)
    threads = torch.get_num_threads()
    runs = []
    try:
        for n in (1, 2, 2):
            torch.set_num_threads(n)
            runs.append(values_and_grads(compiled, planes, lines, u, False))
    finally:
        torch.set_num_threads(threads)
    for other in runs[1:]:
        assert all(torch.equal(a, b) for a, b in zip(runs[0], other, strict=True))


def test_compiled_products_refuse_points_that_need_a_gradient():
    planes, lines = factors(torch.float64)
    with pytest.raises(ValueError, match="no gradient to the points"):
        compiled(planes, lines, points(torch.float64, n=4).requires_grad_(), True)


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_tensorf_cpu_training_step_is_the_same_compiled_or_not(dtype):
    """tensorf-cpu's rendered rays, loss and every parameter's gradient under `--model.kernels compiled` and
    'torch' (a box-shaped grid, its ranks (16, 4, 4) and (48, 12, 12)), to float rounding."""
    base = METHODS["tensorf-cpu"].config
    manager = SyntheticDataManagerConfig(scene=SyntheticSceneConfig(width=24, height=18, num_views=6)).setup(
        data=None, downscale_factor=1)
    batch = manager.next_train_rays(96)
    results = {}
    for kernels in ("compiled", "torch"):
        config = dataclasses.replace(base.model, kernels=kernels, voxels_init=12 ** 3, batch_size=96)
        torch.manual_seed(0)
        model = config.setup(scene=manager.scene, train_indices=manager.train_indices).to(dtype)
        assert model.field.kernels == kernels and len(set(model.field.resolution())) > 1
        model.train()
        torch.manual_seed(1)  # the sampler's jitter
        rays = dataclasses.replace(batch["rays"], origins=batch["rays"].origins.to(dtype),
                                   directions=batch["rays"].directions.to(dtype))
        outputs = model.get_train_outputs({**batch, "rays": rays})
        loss = sum(model.get_loss_dict(outputs, {**batch, "image": batch["image"].to(dtype)}, 1).values())
        loss.backward()
        results[kernels] = [outputs["rgb"].detach(), loss.detach(),
                            *(p.grad for p in model.parameters() if p.grad is not None)]
    tolerance = 1e-12 if dtype == torch.float64 else 1e-5
    assert len(results["compiled"]) == len(results["torch"]) > 2
    for a, b in zip(results["compiled"], results["torch"], strict=True):
        assert float((a - b).abs().max() / b.abs().max()) < tolerance
