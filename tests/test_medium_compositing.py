"""The medium compositor (WaterSplatting's water between depth-sorted Gaussians) against a brute-force loop, its
gradients against autograd of that loop and gradcheck, and its limits: no water is 3DGS, no Gaussians is water."""

from __future__ import annotations

import dataclasses
import warnings
from dataclasses import dataclass

import pytest
import torch
from test_rasterizer import F64, Scene, random_scene
from torch import Tensor

from uw3dgs.cameras import Camera
from uw3dgs.kernels import build as kernel_build
from uw3dgs.kernels.medium_compositing import rasterize_medium_cpu
from uw3dgs.render import RasterSettings, Splats, rasterize
from uw3dgs.render.medium_rasterize import rasterize_medium
from uw3dgs.render.medium_reference import _CompositeMediumTiles, rasterize_medium_reference
from uw3dgs.render.medium_types import PixelMedium
from uw3dgs.render.projection import project_gaussians
from uw3dgs.render.reference import bin_gaussians


def random_medium(seed: int, width: int, height: int, strength: float = 0.3) -> PixelMedium:
    """Smoothly varying water, different per channel, as a direction MLP would give."""
    gen = torch.Generator().manual_seed(seed)
    ramp = torch.linspace(0.5, 1.5, width, dtype=F64)[None, :, None] * torch.linspace(1.2, 0.8, height,
                                                                                        dtype=F64)[:, None, None]
    base = torch.rand(3, generator=gen, dtype=F64)
    return PixelMedium(color=(0.2 + 0.6 * base) * ramp.clamp(max=1.2) / 1.2,
                       sigma_bs=strength * torch.rand(3, generator=gen, dtype=F64) * ramp,
                       sigma_attn=strength * torch.rand(3, generator=gen, dtype=F64) * ramp.flip(1))


@dataclass
class BruteMedium:
    object: Tensor
    medium: Tensor
    restored: Tensor
    alpha: Tensor
    depth: Tensor
    terminated_pixels: int
    terminated: Tensor  # [H, W] bool: the pixels that ended early


def brute_force_medium(scene: Scene, medium: PixelMedium, settings: RasterSettings) -> BruteMedium:
    """Every pixel's Gaussians one at a time front to back, the water written as the interval sum of the definition:
    medium = sum_i T_i (exp(-s z_prev) - exp(-s z_i)) c_med + T_final exp(-s z_last) c_med, z_prev the depth of the
    previous blended Gaussian (0 at the camera); depths detached, as in the compositor."""
    cam = scene.camera
    proj = project_gaussians(scene.means, scene.quats, scene.scales, scene.opacities, cam.viewmat, cam.K, cam.width,
                             cam.height, settings)
    v, u = torch.meshgrid(torch.arange(cam.height), torch.arange(cam.width), indexing="ij")
    pix = torch.stack([u.flatten(), v.flatten()], dim=-1).to(F64) + 0.5
    c_med, s_bs, s_attn = (t.reshape(-1, 3) for t in (medium.color, medium.sigma_bs, medium.sigma_attn))
    n_pix = len(pix)
    T = torch.ones(n_pix, dtype=F64)
    done = torch.zeros(n_pix, dtype=torch.bool)
    z_prev = torch.zeros(n_pix, dtype=F64)
    obj = torch.zeros(n_pix, 3, dtype=F64)
    water = torch.zeros(n_pix, 3, dtype=F64)
    restored = torch.zeros(n_pix, 3, dtype=F64)
    alpha_img = torch.zeros(n_pix, dtype=F64)
    depth_img = torch.zeros(n_pix, dtype=F64)
    depths = proj.depths.detach()
    for i in torch.argsort(depths, stable=True).tolist():
        if not proj.valid[i]:
            continue
        d = pix - proj.means2d[i]
        a, b, c = proj.conics[i]
        power = -0.5 * (a * d[:, 0] ** 2 + c * d[:, 1] ** 2) - b * d[:, 0] * d[:, 1]
        alpha = torch.clamp(scene.opacities[i] * torch.exp(power), max=settings.alpha_max)
        skip = (power > 0) | (alpha < settings.alpha_min) | done
        t_next = T * (1 - alpha)
        stop = ~skip & (t_next < settings.transmittance_min)
        done = done | stop
        blend = (~skip & ~stop)[:, None]
        w = alpha * T
        z = depths[i]
        obj = obj + torch.where(blend, w[:, None] * scene.features[i] * torch.exp(-s_attn * z), 0.0)
        interval = torch.exp(-s_bs * z_prev[:, None]) - torch.exp(-s_bs * z)
        water = water + torch.where(blend, T[:, None] * interval * c_med, 0.0)
        restored = restored + torch.where(blend, w[:, None] * scene.features[i], 0.0)
        alpha_img = alpha_img + torch.where(blend[:, 0], w, 0.0)
        depth_img = depth_img + torch.where(blend[:, 0], w * z, 0.0)
        z_prev = torch.where(blend[:, 0], z, z_prev)
        T = torch.where(blend[:, 0], t_next, T)
    water = water + T[:, None] * torch.exp(-s_bs * z_prev[:, None]) * c_med  # behind the last one, to infinity
    shape = (cam.height, cam.width)
    return BruteMedium(object=obj.reshape(*shape, 3), medium=water.reshape(*shape, 3),
                       restored=restored.reshape(*shape, 3), alpha=alpha_img.reshape(shape),
                       depth=depth_img.reshape(shape), terminated_pixels=int(done.sum()),
                       terminated=done.reshape(shape))


def render_reference(scene: Scene, medium: PixelMedium, settings: RasterSettings, **kwargs):
    cam = scene.camera
    return rasterize_medium_reference(Splats(*scene.inputs()), medium, cam, settings, **kwargs)


def _scene_and_medium(seed: int, n: int, width: int = 40, height: int = 30) -> tuple[Scene, PixelMedium]:
    scene = random_scene(seed, n, width, height)
    scene.features = scene.features.clamp(0, 1)
    return scene, random_medium(seed, scene.camera.width, scene.camera.height)


TERMINATING = RasterSettings(backend="torch", tile_size=8, transmittance_min=0.2)
"""Ends most pixels of `_scene_and_medium(2, 100)` after a few Gaussians: the tail term then starts at the last blended
Gaussian's depth, with the transmittance left there."""


@pytest.mark.parametrize("seed,n,settings", [(0, 60, RasterSettings(backend="torch", tile_size=16)),
                                             (0, 60, RasterSettings(backend="torch", tile_size=8)),
                                             (2, 100, TERMINATING)])
def test_reference_matches_brute_force(seed: int, n: int, settings: RasterSettings) -> None:
    scene, medium = _scene_and_medium(seed, n)
    out = render_reference(scene, medium, settings)
    ref = brute_force_medium(scene, medium, settings)
    for name, got in (("object", out.object), ("medium", out.medium), ("restored", out.render),
                      ("alpha", out.alpha), ("depth", out.depth)):
        torch.testing.assert_close(got, getattr(ref, name), rtol=0, atol=1e-10, msg=name)
    if settings is TERMINATING:
        assert ref.terminated_pixels > 200
    else:
        assert ref.alpha.max() > 0.99 and ref.alpha.min() < 0.7  # the water shows through


def test_no_water_is_3dgs_and_no_gaussians_is_water() -> None:
    scene, medium = _scene_and_medium(0, 60)
    settings = RasterSettings(backend="torch")
    cam = scene.camera
    clear = PixelMedium(color=medium.color, sigma_bs=torch.zeros_like(medium.sigma_bs),
                        sigma_attn=torch.zeros_like(medium.sigma_attn))
    out = render_reference(scene, clear, settings)
    plain = rasterize(scene.splats(), cam, settings)
    assert torch.equal(out.render, plain.render) and torch.equal(out.alpha, plain.alpha)
    torch.testing.assert_close(out.object, plain.render, rtol=0, atol=1e-15)
    # the water is then the background composited behind the Gaussians, c_med (1 - alpha)
    torch.testing.assert_close(out.medium, medium.color * (1 - plain.alpha[..., None]), rtol=0, atol=1e-15)

    behind = Scene(scene.means, scene.quats, scene.scales, scene.opacities * 0, scene.features, cam)
    empty = render_reference(behind, medium, settings)
    assert torch.equal(empty.medium, medium.color) and not empty.object.any() and not empty.alpha.any()


LOSS_SEED = 5


def _loss(out_object: Tensor, out_medium: Tensor, restored: Tensor, alpha: Tensor, depth: Tensor) -> Tensor:
    gen = torch.Generator().manual_seed(LOSS_SEED)
    return sum((t * torch.randn(t.shape, generator=gen, dtype=F64)).sum()
               for t in (out_object, out_medium, restored, alpha, depth))


def test_gradients_match_brute_force_autograd() -> None:
    scene, medium = _scene_and_medium(2, 100)
    settings = TERMINATING
    leaves = [t.clone().requires_grad_(True) for t in scene.inputs()]
    water = [t.clone().requires_grad_(True) for t in (medium.color, medium.sigma_bs, medium.sigma_attn)]
    leaf_scene = Scene(*leaves, camera=scene.camera)
    out = render_reference(leaf_scene, PixelMedium(*water), settings)
    grads = torch.autograd.grad(_loss(out.object, out.medium, out.render, out.alpha, out.depth), leaves + water)
    ref = brute_force_medium(leaf_scene, PixelMedium(*water), settings)
    assert ref.terminated_pixels > 0
    ref_grads = torch.autograd.grad(_loss(ref.object, ref.medium, ref.restored, ref.alpha, ref.depth),
                                    leaves + water)
    names = ("means", "quats", "scales", "opacities", "colors", "c_med", "sigma_bs", "sigma_attn")
    for name, g, r in zip(names, grads, ref_grads, strict=True):
        assert r.abs().sum() > 0, name
        torch.testing.assert_close(g, r, rtol=1e-8, atol=1e-9, msg=name)


def test_gradcheck_tiny_scene() -> None:
    """The compositing step alone (screen-space Gaussians in, depths fixed: they take no gradient), three overlapping
    Gaussians in a 12 x 10 view with water in every pixel, against float64 finite differences."""
    gen = torch.Generator().manual_seed(3)
    means = torch.tensor([[0.1, -0.05, 2.0], [-0.2, 0.1, 2.5], [0.25, 0.15, 3.0]], dtype=F64)
    quats = torch.randn(3, 4, generator=gen, dtype=F64)
    scales = torch.tensor([[0.15, 0.08, 0.1], [0.1, 0.2, 0.05], [0.2, 0.12, 0.3]], dtype=F64)
    opacities = torch.tensor([0.5, 0.6, 0.4], dtype=F64)
    colors = torch.rand(3, 3, generator=gen, dtype=F64)
    K = torch.tensor([[10.0, 0, 6.2], [0, 11.0, 4.9], [0, 0, 1]], dtype=F64)
    settings = RasterSettings(backend="torch", tile_size=8)
    proj = project_gaussians(means, quats, scales, opacities, torch.eye(4, dtype=F64), K, 12, 10, settings)
    bins = bin_gaussians(proj, 12, 10, settings.tile_size)
    medium = random_medium(4, 12, 10, strength=0.5)

    def composite(means2d, conics, opacities, colors, water):
        images = _CompositeMediumTiles.apply(means2d, conics, opacities, colors, proj.depths, water, bins, 12, 10,
                                             settings, None)
        return images[:3]

    inputs = tuple(t.detach().clone().requires_grad_(True)
                   for t in (proj.means2d, proj.conics, opacities, colors, medium.packed()))
    assert torch.autograd.gradcheck(composite, inputs, eps=1e-6, atol=1e-7, rtol=1e-5, fast_mode=True)


PIXELS = ((3, 5), (12, 20), (20, 33), (27, 8))


def test_absgrad_sums_per_pixel_gradients() -> None:
    """absgrad = sum over pixels of |dL/dmeans2d| per pixel: at least |dL/dmeans2d|, equal for a one-pixel view."""
    scene, medium = _scene_and_medium(0, 60)
    settings = RasterSettings(backend="torch", tile_size=8)
    leaves = [t.clone().requires_grad_(True) for t in scene.inputs()]
    out = render_reference(Scene(*leaves, camera=scene.camera), medium, settings, absgrad=True)
    out.means2d.retain_grad()
    assert not out.absgrad.any()
    _loss(out.object, out.medium, out.render, out.alpha, out.depth).backward()
    grad = out.means2d.grad
    assert out.absgrad.shape == grad.shape and (out.absgrad > 0).any()
    assert (out.absgrad >= grad.abs() - 1e-12).all()
    assert (out.absgrad > grad.abs() * 1.01).any()  # signs do cancel across pixels
    # every pixel's gradient alone: render with the loss on one pixel, sum the absolute values
    mask_total = torch.zeros_like(grad)
    for v, u in PIXELS:
            single = render_reference(Scene(*leaves, camera=scene.camera), medium, settings)
            single.means2d.retain_grad()
            (single.object[v, u].sum() + single.medium[v, u].sum()).backward()
            mask_total += single.means2d.grad.abs()
    ones = render_reference(Scene(*leaves, camera=scene.camera), medium, settings, absgrad=True)
    sparse = torch.zeros_like(ones.object)
    for v, u in PIXELS:
        sparse[v, u] = 1.0
    ((ones.object + ones.medium) * sparse).sum().backward()
    torch.testing.assert_close(ones.absgrad, mask_total, rtol=1e-9, atol=1e-12)


def _compiled():
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        if kernel_build.load_extension() is None:
            pytest.skip(f"the C++ CPU module could not be built here: {kernel_build._state.get('error')}")


def _render_with_grads(fn, scene: Scene, medium: PixelMedium, dtype: torch.dtype, settings: RasterSettings):
    """Outputs and every input's gradient (and absgrad) under a random linear loss of all five images."""
    leaves = [t.to(dtype).clone().requires_grad_(True) for t in scene.inputs()]
    water = [t.to(dtype).clone().requires_grad_(True) for t in (medium.color, medium.sigma_bs, medium.sigma_attn)]
    cam = scene.camera
    cam = Camera(cam.viewmat.to(dtype), cam.K.to(dtype), cam.width, cam.height)
    out = fn(Splats(*leaves), PixelMedium(*water), cam, settings, absgrad=True)
    out.means2d.retain_grad()
    gen = torch.Generator().manual_seed(LOSS_SEED)
    sum((t * torch.randn(t.shape, generator=gen, dtype=F64).to(dtype)).sum()
        for t in (out.object, out.medium, out.render, out.alpha, out.depth)).backward()
    return out, [t.grad for t in leaves + water] + [out.means2d.grad, out.absgrad]


WHOLE_TILES_END = RasterSettings(tile_size=8, transmittance_min=0.6)
"""Ends every pixel of many tiles of `_scene_and_medium(2, 100)` before their lists end: the tile stops early."""


@pytest.mark.parametrize("dtype", [F64, torch.float32], ids=["f64", "f32"])
@pytest.mark.parametrize("seed,n,settings,size", [
    (0, 60, RasterSettings(tile_size=16), (40, 30)),
    (2, 100, TERMINATING, (40, 30)),
    (2, 100, WHOLE_TILES_END, (40, 30)),
    (3, 4, RasterSettings(tile_size=8), (37, 23)),  # most tiles empty: pure water there; tiles cut by the border
    (1, 2000, RasterSettings(tile_size=16), (40, 30)),
], ids=["tile16", "terminating", "whole-tiles-end", "empty-tiles", "dense"])
def test_compiled_matches_reference(seed: int, n: int, settings: RasterSettings, size: tuple[int, int],
                                    dtype: torch.dtype) -> None:
    """Every output, every gradient (the medium's too) and the absolute gradients of the compiled compositor equal
    the reference's: to 1e-9 relative in float64, 1e-4 in float32 (integers exactly)."""
    _compiled()
    from test_rasterizer import assert_close_rel

    scene, medium = _scene_and_medium(seed, n, *size)
    settings = dataclasses.replace(settings, backend="cpu")
    out, grads = _render_with_grads(rasterize_medium_cpu, scene, medium, dtype, settings)
    ref, ref_grads = _render_with_grads(rasterize_medium_reference, scene, medium, dtype, settings)
    for name in ("object", "medium", "render", "alpha", "depth", "means2d", "depths", "conics", "weight_sum"):
        assert_close_rel(getattr(out, name).detach(), getattr(ref, name).detach(), dtype, name)
    assert torch.equal(out.radii, ref.radii) and torch.equal(out.pixel_count, ref.pixel_count)
    names = ("means", "quats", "scales", "opacities", "colors", "c_med", "sigma_bs", "sigma_attn", "means2d", "absgrad")
    for name, got, want in zip(names, grads, ref_grads, strict=True):
        assert want.abs().sum() > 0, name
        assert_close_rel(got, want, dtype, f"grad {name}")
    # without a gradient no trace is recorded: the same images, bit for bit
    cam = scene.camera
    with torch.no_grad():
        plain = rasterize_medium_cpu(Splats(*(t.to(dtype) for t in scene.inputs())),
                                     PixelMedium(*(t.to(dtype) for t in (medium.color, medium.sigma_bs,
                                                                          medium.sigma_attn))),
                                     Camera(cam.viewmat.to(dtype), cam.K.to(dtype), cam.width, cam.height), settings)
    for name in ("object", "medium", "render", "alpha", "depth", "weight_sum", "pixel_count"):
        assert torch.equal(getattr(plain, name), getattr(out, name).detach()), name


def test_compiled_is_bitwise_the_same_on_any_thread_count() -> None:
    """Outputs, gradients (the medium's too) and absolute gradients, run again and on one and two threads: enough
    pairs for the parallel paths (kParallelMin = 4,096 in common.h)."""
    _compiled()
    scene, medium = _scene_and_medium(8, 6000, 96, 80)
    settings = RasterSettings(backend="cpu")
    threads = torch.get_num_threads()
    runs = []
    try:
        for n_threads in (threads, threads, 1, max(2, threads)):
            torch.set_num_threads(n_threads)
            out, grads = _render_with_grads(rasterize_medium_cpu, scene, medium, torch.float32, settings)
            runs.append([out.object, out.medium, out.render, out.alpha, out.depth, out.weight_sum, out.pixel_count,
                         *grads])
    finally:
        torch.set_num_threads(threads)
    cam = scene.camera
    proj = project_gaussians(scene.means, scene.quats, scene.scales, scene.opacities, cam.viewmat, cam.K, cam.width,
                             cam.height, settings)
    assert int(bin_gaussians(proj, cam.width, cam.height, settings.tile_size).tile_counts.sum()) > 4 * 4096
    for other in runs[1:]:
        for a, b in zip(runs[0], other, strict=True):
            assert torch.equal(a, b)


def test_compiled_cases_reach_their_paths() -> None:
    """The cases above do what their names say: tiles without Gaussians, tiles whose every pixel terminates."""
    scene, medium = _scene_and_medium(3, 4, 37, 23)
    ref = brute_force_medium(scene, medium, RasterSettings(tile_size=8))
    cam = scene.camera
    proj = project_gaussians(scene.means, scene.quats, scene.scales, scene.opacities, cam.viewmat, cam.K, cam.width,
                             cam.height, RasterSettings(tile_size=8))
    bins = bin_gaussians(proj, cam.width, cam.height, 8)
    assert (bins.tile_counts == 0).sum() >= 4 and ref.alpha.max() > 0.3
    scene, medium = _scene_and_medium(2, 100)
    ref = brute_force_medium(scene, medium, WHOLE_TILES_END)
    ended = ref.terminated.unfold(0, 8, 8).unfold(1, 8, 8).all(-1).all(-1)  # whole 8 x 8 tiles
    assert ended.sum() >= 2


SERIES_BOUNDS = {F64: 1 / 16, torch.float32: 1 / 8}
"""medium_compositing.cpp's WaterSeries bounds: a (tile, Gaussian) pair whose depth times its tile's largest half-range
of sigma is within takes its water factors as one exp at the tile's midrange times a short series, else an exp per
pixel."""


def _pairs_by_water_path(seed: int, n: int, settings: RasterSettings, size: tuple[int, int],
                         bound: float) -> tuple[int, int]:
    """(pairs on the series path, pairs on the exp-per-pixel path) of `_scene_and_medium(seed, n, *size)`."""
    scene, medium = _scene_and_medium(seed, n, *size)
    cam, ts = scene.camera, settings.tile_size
    proj = project_gaussians(scene.means, scene.quats, scene.scales, scene.opacities, cam.viewmat, cam.K, cam.width,
                             cam.height, settings)
    bins = bin_gaussians(proj, cam.width, cam.height, ts)
    sigma = torch.cat([medium.sigma_bs, medium.sigma_attn], dim=-1)
    spread = torch.stack([(sigma[y:y + ts, x:x + ts].amax((0, 1)) - sigma[y:y + ts, x:x + ts].amin((0, 1))).max() / 2
                          for y in range(0, cam.height, ts) for x in range(0, cam.width, ts)])
    tiles = torch.repeat_interleave(torch.arange(len(bins.tile_counts)), bins.tile_counts)
    series = spread[tiles] * proj.depths[bins.gauss_ids].abs() <= bound
    return int(series.sum()), int((~series).sum())


@pytest.mark.parametrize("dtype", [F64, torch.float32], ids=["f64", "f32"])
def test_compiled_cases_take_both_water_paths(dtype: torch.dtype) -> None:
    """test_compiled_matches_reference's tile16 and dense cases have many (tile, Gaussian) pairs on each path of the
    water factors, so both are held to the reference there."""
    for seed, n in ((0, 60), (1, 2000)):
        series, exact = _pairs_by_water_path(seed, n, RasterSettings(tile_size=16), (40, 30), SERIES_BOUNDS[dtype])
        assert series >= 10 and exact >= 10, (seed, n, series, exact)


def test_dispatch_picks_compiled_on_cpu_and_refuses_gsplat(monkeypatch: pytest.MonkeyPatch) -> None:
    _compiled()
    from uw3dgs.kernels import medium_compositing as medium_cpu

    calls = []
    compiled = medium_cpu.rasterize_medium_cpu
    monkeypatch.setattr(medium_cpu, "rasterize_medium_cpu", lambda *a, **k: calls.append(1) or compiled(*a, **k))
    scene, medium = _scene_and_medium(0, 60)
    cam = scene.camera
    rasterize_medium(Splats(*scene.inputs()), medium, cam, RasterSettings())
    rasterize_medium(Splats(*scene.inputs()), medium, cam, RasterSettings(backend="cpu"))
    assert len(calls) == 2
    rasterize_medium(Splats(*scene.inputs()), medium, cam, RasterSettings(backend="torch"))
    assert len(calls) == 2
    with pytest.raises(ValueError, match="gsplat"):
        rasterize_medium(Splats(*scene.inputs()), medium, cam, RasterSettings(backend="gsplat"))
