"""The ray-marching renderer (uw3dgs/raymarch/): compositors against float64 loops, the TensoRF field's VM reads
against a dense grid, the occupancy grid's guarantee, the NDC sampler's world distances, and ray batches against the
views the Gaussian datamanager serves."""

from __future__ import annotations

import math

import pytest
import torch
from test_datamanagers import make_dataset

from uw3dgs.datamanagers.colmap import ColmapDataManagerConfig
from uw3dgs.datamanagers.seathru_nerf import SeathruNerfDataManagerConfig
from uw3dgs.datamanagers.synthetic import SyntheticDataManagerConfig
from uw3dgs.fields.tensorf import LINE_AXES, PLANE_AXES, TensoRFFieldConfig, vm_products
from uw3dgs.raymarch.compositing import composite, composite_underwater, volume_weights
from uw3dgs.raymarch.occupancy import OccupancyGrid
from uw3dgs.raymarch.rays import RayBundle
from uw3dgs.raymarch.samplers import NDCSampler, average_camera

# ----------------------------------------------------------------------------------------------------
# Compositors


def random_ray(samples: int = 12, seed: int = 0, inf_tail: bool = False):
    g = torch.Generator().manual_seed(seed)
    sigma = torch.rand(1, samples, generator=g, dtype=torch.float64) * 2
    sigma[0, ::3] = 0.0  # empty stretches
    deltas = torch.rand(1, samples, generator=g, dtype=torch.float64) * 0.5
    deltas[0, -1] = 0.0  # TensoRF's last interval
    ranges = 0.3 + torch.cumsum(torch.rand(1, samples, generator=g, dtype=torch.float64), dim=1)
    if inf_tail:
        ranges[0, -2:] = math.inf  # NDC samples at or past infinity
    rgb = torch.rand(1, samples, 3, generator=g, dtype=torch.float64)
    medium = [torch.rand(1, 3, generator=g, dtype=torch.float64) * s for s in (0.8, 0.5, 1.0)]
    return sigma, deltas, ranges, rgb, medium


def brute_force(sigma, deltas, ranges, rgb, sigma_attn, sigma_bs, c_med):
    """One ray, sample by sample, in float64: (standard colour, underwater colour)."""
    color, water, transmittance = torch.zeros(3, dtype=torch.float64), torch.zeros(3, dtype=torch.float64), 1.0
    s = [float(r) for r in ranges[0]] + [math.inf]
    def decay(k, dist):
        return 0.0 if math.isinf(dist) and k > 0 else math.exp(-k * dist) if not math.isinf(dist) else 1.0
    for i in range(sigma.shape[1]):
        alpha = 1 - math.exp(-float(sigma[0, i]) * float(deltas[0, i]))
        for c in range(3):
            color[c] += transmittance * alpha * rgb[0, i, c]
            water[c] += transmittance * alpha * rgb[0, i, c] * decay(float(sigma_attn[0, c]), s[i])
            bs = float(sigma_bs[0, c])
            water[c] += transmittance * (decay(bs, s[i]) - decay(bs, s[i + 1])) * c_med[0, c]
        transmittance *= 1 - alpha
    for c in range(3):  # the water between the camera and the first sample
        water[c] += (1 - decay(float(sigma_bs[0, c]), s[0])) * c_med[0, c]
    return color, water


@pytest.mark.parametrize("inf_tail", [False, True])
def test_compositors_match_a_float64_loop_along_one_ray(inf_tail):
    sigma, deltas, ranges, rgb, (sigma_attn, sigma_bs, c_med) = random_ray(inf_tail=inf_tail)
    weights, trans = volume_weights(sigma, deltas)
    color, acc = composite(weights, rgb)
    out = composite_underwater(weights, trans, rgb, ranges, sigma_attn, sigma_bs, c_med)
    want_color, want_water = brute_force(sigma, deltas, ranges, rgb, sigma_attn, sigma_bs, c_med)
    torch.testing.assert_close(color[0], want_color, rtol=1e-12, atol=1e-12)
    torch.testing.assert_close(out.rgb[0], want_water, rtol=1e-12, atol=1e-12)
    torch.testing.assert_close(out.restored, color)
    assert 0 < float(acc) < 1


def test_underwater_compositor_with_zero_medium_is_volume_rendering():
    sigma, deltas, ranges, rgb, (_, _, c_med) = random_ray(seed=1, inf_tail=True)
    weights, trans = volume_weights(sigma, deltas)
    zero = torch.zeros(1, 3, dtype=torch.float64)
    out = composite_underwater(weights, trans, rgb, ranges, zero, zero, c_med)
    torch.testing.assert_close(out.rgb, composite(weights, rgb)[0], rtol=0, atol=1e-15)
    assert float(out.backscatter.abs().max()) == 0.0


@pytest.mark.parametrize("inf_tail", [False, True])
def test_an_empty_ray_sees_pure_water(inf_tail):
    sigma, deltas, ranges, rgb, (sigma_attn, sigma_bs, c_med) = random_ray(seed=2, inf_tail=inf_tail)
    weights, trans = volume_weights(torch.zeros_like(sigma), deltas)
    out = composite_underwater(weights, trans, rgb, ranges, sigma_attn, sigma_bs, c_med)
    torch.testing.assert_close(out.rgb, c_med, rtol=1e-12, atol=1e-12)


def test_underwater_gradients_are_finite_with_infinite_ranges():
    sigma, deltas, ranges, rgb, medium = random_ray(seed=3, inf_tail=True)
    medium = [m.requires_grad_() for m in medium]
    sigma.requires_grad_()
    weights, trans = volume_weights(sigma, deltas)
    composite_underwater(weights, trans, rgb, ranges, *medium).rgb.sum().backward()
    for t in (sigma, *medium):
        assert torch.isfinite(t.grad).all() and t.grad.abs().sum() > 0


# ----------------------------------------------------------------------------------------------------
# The TensoRF field and the occupancy grid


def tiny_field(resolution=(5, 6, 7), activation="relu", dtype=torch.float64):
    config = TensoRFFieldConfig(density_components=(3, 2, 2), appearance_components=(4, 3, 2), appearance_dim=5,
                                hidden=8, density_activation=activation, init_scale=0.5)
    torch.manual_seed(0)
    field = config.setup(lo=torch.tensor([-1.0, -2.0, 0.5]), hi=torch.tensor([2.0, 1.0, 3.0]), resolution=resolution)
    return field.to(dtype)


def dense_density_feature(field) -> torch.Tensor:
    """The summed VM feature at every grid vertex [X, Y, Z], built from the factors by outer products."""
    total = 0
    for m, ((a, b), c) in enumerate(zip(PLANE_AXES, LINE_AXES, strict=True)):
        plane, line = field.density_planes[m][0], field.density_lines[m][0, :, :, 0]  # [R, G_b, G_a], [R, G_c]
        product = torch.einsum("rba,rc->rabc", plane, line).sum(0)  # axes (a, b, c)
        order = [None, None, None]
        order[a], order[b], order[c] = 0, 1, 2
        total = total + product.permute(*order)
    return total


def trilinear(grid: torch.Tensor, u: torch.Tensor) -> torch.Tensor:
    """grid [X, Y, Z] read at u [N, 3] in [-1, 1]^3 (vertices at the ends: align_corners), by the 8-corner formula."""
    size = torch.tensor(grid.shape, dtype=u.dtype)
    pos = (u + 1) / 2 * (size - 1)
    i0 = pos.floor().long().clamp(max=(size - 2).long())
    f = pos - i0
    out = 0
    for corner in range(8):
        bits = [(corner >> k) & 1 for k in range(3)]
        w = torch.ones(len(u), dtype=u.dtype)
        for k in range(3):
            w = w * (f[:, k] if bits[k] else 1 - f[:, k])
        out = out + w * grid[i0[:, 0] + bits[0], i0[:, 1] + bits[1], i0[:, 2] + bits[2]]
    return out


def test_vm_density_reads_and_gradients_match_a_dense_grid():
    field = tiny_field()
    x = field.lo + torch.rand(200, 3, dtype=torch.float64) * (field.hi - field.lo)
    u = field.normalize(x)
    read = field.density_feature(u)
    reference = trilinear(dense_density_feature(field), u)
    torch.testing.assert_close(read, reference, rtol=1e-10, atol=1e-12)
    weights = torch.rand(200, dtype=torch.float64)
    grads = torch.autograd.grad((read * weights).sum(), list(field.density_planes) + list(field.density_lines))
    ref_grads = torch.autograd.grad((reference * weights).sum(),
                                    list(field.density_planes) + list(field.density_lines))
    for g, r in zip(grads, ref_grads, strict=True):
        torch.testing.assert_close(g, r, rtol=1e-10, atol=1e-12)


def test_sh_shading_is_tensorfs_shrender_written_out():
    """shading 'sh': relu(sum_k f[c, k] Y_k(d) + 0.5) with the 9 degree-2 harmonics, features channel-major (TensoRF's
    `features.view(-1, 3, 9)`), against the harmonics written out here from their closed forms, values and
    gradients."""
    config = TensoRFFieldConfig(density_components=(2, 2, 2), appearance_components=(4, 3, 2), shading="sh",
                                init_scale=0.5)
    torch.manual_seed(1)
    field = config.setup(lo=torch.tensor([-1.0, -2.0, 0.5]), hi=torch.tensor([2.0, 1.0, 3.0]),
                         resolution=(4, 5, 6)).double()
    assert field.mlp is None and set(field.param_groups()["field_networks"]) == set(field.basis.parameters())
    x = field.lo + torch.rand(64, 3, dtype=torch.float64) * (field.hi - field.lo)
    d = torch.nn.functional.normalize(torch.randn(64, 3, dtype=torch.float64), dim=-1)
    rgb = field.color(x, d)
    features = field.basis(torch.cat(vm_products(field.app_planes, field.app_lines, field.normalize(x)), dim=-1))
    dx, dy, dz = d.unbind(-1)
    harmonics = torch.stack([torch.full_like(dx, 0.5 / math.sqrt(math.pi)),
                             -math.sqrt(3 / (4 * math.pi)) * dy, math.sqrt(3 / (4 * math.pi)) * dz,
                             -math.sqrt(3 / (4 * math.pi)) * dx,
                             0.5 * math.sqrt(15 / math.pi) * dx * dy, -0.5 * math.sqrt(15 / math.pi) * dy * dz,
                             0.25 * math.sqrt(5 / math.pi) * (2 * dz * dz - dx * dx - dy * dy),
                             -0.5 * math.sqrt(15 / math.pi) * dx * dz,
                             0.25 * math.sqrt(15 / math.pi) * (dx * dx - dy * dy)],
                            dim=-1)
    expected = torch.relu(torch.einsum("nck,nk->nc", features.reshape(64, 3, 9), harmonics) + 0.5)
    torch.testing.assert_close(rgb, expected, rtol=1e-12, atol=1e-12)
    grads = torch.autograd.grad(rgb.sum(), list(field.app_planes) + [field.basis.weight])
    ref = torch.autograd.grad(expected.sum(), list(field.app_planes) + [field.basis.weight])
    for g, r in zip(grads, ref, strict=True):
        torch.testing.assert_close(g, r, rtol=1e-10, atol=1e-12)


def test_sh_shading_needs_27_appearance_features():
    with pytest.raises(ValueError, match="must be 27 with shading 'sh'"):
        TensoRFFieldConfig(shading="sh", appearance_dim=12)


@pytest.mark.parametrize("parent", ["tensorf", "seathru-nerf"])
def test_cpu_preset_differs_from_its_parent_only_in_the_cpu_recipe(parent):
    from test_ablations import differing_fields

    from uw3dgs.registry import METHODS

    differ = differing_fields(METHODS[parent].config, METHODS[f"{parent}-cpu"].config)  # the method's name aside
    assert differ == {"max_num_iterations", "model.radiance.shading", "model.batch_size",
                      "model.voxels_init", "model.voxels_final", "model.upsample_steps", "model.alpha_mask_steps",
                      "model.step_ratio", "model.max_samples"}


def test_upsampling_keeps_the_field_at_the_old_vertices_interpolated():
    field = tiny_field(resolution=(3, 3, 3))
    x = field.lo + torch.rand(50, 3, dtype=torch.float64) * (field.hi - field.lo)
    before = field.density_feature(field.normalize(x))
    field.upsample((5, 5, 5))  # the old vertices are among the new ones: a trilinear field is unchanged
    assert field.resolution() == (5, 5, 5)
    torch.testing.assert_close(field.density_feature(field.normalize(x)), before, rtol=1e-10, atol=1e-12)


@pytest.mark.parametrize("activation", ["relu", "softplus"])
def test_occupancy_grid_never_skips_a_sample_above_its_threshold(activation):
    field = tiny_field(resolution=(6, 5, 7), activation=activation)
    with torch.no_grad():
        step = 0.05
        vertices = torch.stack(torch.meshgrid(*[torch.linspace(float(field.lo[k]), float(field.hi[k]), n)
                                                for k, n in enumerate(field.resolution())], indexing="ij"), -1)
        alpha = -torch.expm1(-field.density(vertices.reshape(-1, 3).double()) * step)
        threshold = float(alpha.quantile(0.7))  # most vertices empty: the grid must skip something
        grid = OccupancyGrid(field.lo, field.hi)
        grid.build(field.density, field.lo, field.hi, field.resolution(), step, threshold, dilation=1)
        x = field.lo + torch.rand(20000, 3, dtype=torch.float64) * (field.hi - field.lo)
        dense = -torch.expm1(-field.density(x) * step) >= threshold
        occupied = grid.occupied(x)
    assert dense.any() and not occupied.all()
    assert bool(occupied[dense].all())


def test_occupied_bounds_are_the_extreme_occupied_vertices():
    grid = OccupancyGrid(torch.tensor([0.0, -1.0, 2.0]), torch.tensor([4.0, 1.0, 3.0]))
    grid.build(lambda x: ((x[:, 0] - 1.0).abs() < 0.1).double() + (x[:, 1] > 0.6).double() * (x[:, 2] < 2.3),
               grid.lo, grid.hi, (5, 11, 6), step=1.0, threshold=0.5, dilation=1)
    lo, hi = grid.occupied_bounds()
    # x = 1 occupied everywhere in y, z; y > 0.6 only where z < 2.3: the vertices x in {1}, y in [-1, 1], z in [2, 3]
    torch.testing.assert_close(lo, torch.tensor([0.0, -1.0, 2.0]))
    torch.testing.assert_close(hi, torch.tensor([4.0, 1.0, 3.0]))
    plane = OccupancyGrid(grid.lo, grid.hi)
    plane.build(lambda x: ((x[:, 0] - 1.0).abs() < 0.1).double(), grid.lo, grid.hi, (5, 11, 6), 1.0, 0.5, dilation=1)
    lo, hi = plane.occupied_bounds()
    torch.testing.assert_close(lo, torch.tensor([1.0, -1.0, 2.0]))
    torch.testing.assert_close(hi, torch.tensor([1.0, 1.0, 3.0]))


# ----------------------------------------------------------------------------------------------------
# Rays


def test_ndc_samples_lie_on_their_world_rays(tiny_scene_config, cache_dir):
    dm = SyntheticDataManagerConfig(scene=tiny_scene_config, cache_dir=cache_dir).setup(data=None)
    cameras = [dm.cameras[i] for i in dm.train_indices]
    R, center = average_camera(cameras)
    cam = cameras[0]
    near = 0.75 * float(dm.scene.near)
    sampler = NDCSampler(R, center, float(cam.K[0, 0]), float(cam.K[1, 1]), cam.width, cam.height, near,
                         torch.tensor([-1.5, -1.67, -1.0]), torch.tensor([1.5, 1.67, 1.0]))
    dirs = cameras[3].ray_directions().reshape(-1, 3)[::7]
    rays = RayBundle(cameras[3].center.expand_as(dirs), dirs, torch.zeros(len(dirs), dtype=torch.long))
    samples = sampler(rays, 16, jitter=False)
    finite = torch.isfinite(samples.ranges)
    world = rays.origins[:, None] + samples.ranges[..., None].clamp(max=1e6) * rays.directions[:, None]
    local = (world - center) @ R.T
    ndc = torch.stack([sampler.ax * local[..., 0] / local[..., 2], sampler.ay * local[..., 1] / local[..., 2],
                       1 - 2 * near / local[..., 2]], dim=-1)
    torch.testing.assert_close(ndc[finite], samples.points[finite], rtol=1e-4, atol=1e-4)
    assert finite[:, :-1].all() and not finite[:, -1].any()  # t = 1 is infinitely far
    assert (samples.ranges[:, 1:-1] > samples.ranges[:, :-2]).all()


def _datamanager(kind, tmp_path, tiny_scene_config, cache_dir):
    if kind == "synthetic":
        return SyntheticDataManagerConfig(scene=tiny_scene_config, cache_dir=cache_dir).setup(data=None, seed=3)
    root = make_dataset(tmp_path / "data", layout="colmap" if kind == "colmap" else "seathru", views=9,
                        llff=kind == "seathru-nerf")
    config = ColmapDataManagerConfig if kind == "colmap" else SeathruNerfDataManagerConfig
    return config(cache_dir=tmp_path / "cache").setup(data=root, seed=3)


@pytest.mark.parametrize("kind", ["synthetic", "colmap", "seathru-nerf"])
def test_ray_batches_are_the_training_views_pixels(kind, tmp_path, tiny_scene_config, cache_dir):
    dm = _datamanager(kind, tmp_path, tiny_scene_config, cache_dir)
    height, width = dm.images.shape[1:3]
    per_epoch = len(dm.train_indices) * height * width
    batch = 97
    seen = torch.zeros(len(dm.images), height * width, dtype=torch.long)
    views_all = [dm.get_batch(i) for i in range(len(dm.images))]  # what the Gaussian methods get, view by view
    colors = torch.stack([v["image"].reshape(-1, 3) for v in views_all])
    directions = torch.stack([v["camera"].ray_directions().reshape(-1, 3) for v in views_all])
    centers = torch.stack([v["camera"].center for v in views_all])
    for _ in range(per_epoch // batch):
        b = dm.next_train_rays(batch)
        views, pixels = b["rays"].camera_indices, b["pixels"]
        seen[views, pixels] += 1
        torch.testing.assert_close(b["image"], colors[views, pixels], rtol=0, atol=0)
        torch.testing.assert_close(b["rays"].directions, directions[views, pixels])
        torch.testing.assert_close(b["rays"].origins, centers[views])
    assert set(torch.nonzero(seen.sum(1)).flatten().tolist()) <= set(dm.train_indices)
    assert seen.max() == 1 and seen.sum() == (per_epoch // batch) * batch  # no pixel twice in an epoch
    assert not set(dm.test_indices) & set(torch.nonzero(seen.sum(1)).flatten().tolist())


def test_ray_batches_resume_the_same_draws(tiny_scene_config, cache_dir):
    def make():
        return SyntheticDataManagerConfig(scene=tiny_scene_config, cache_dir=cache_dir).setup(data=None, seed=5)
    a, b = make(), make()
    a.next_train_rays(1000)
    state = a.state_dict()
    b.load_state_dict(state)
    total = len(a.train_indices) * a.images.shape[1] * a.images.shape[2]
    for _ in range(total // 1000 + 2):  # across an epoch boundary
        torch.testing.assert_close(a.next_train_rays(1000)["pixels"], b.next_train_rays(1000)["pixels"], rtol=0,
                                   atol=0)
