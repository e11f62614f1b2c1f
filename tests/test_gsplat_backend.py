"""The gsplat backend ('gsplat') against the torch reference.

- CUDA parity (real gsplat kernels): skipped unless CUDA and gsplat are both available.
- Glue, on any machine with gsplat installed: the backend's gsplat functions are swapped for PyTorch versions
  on CPU tensors -- gsplat's own `_isect_tiles` / `_isect_offset_encode` from `gsplat.cuda._torch_impl`, and,
  where gsplat has no CPU-capable version (`rasterize_to_indices_in_range` has none; its `_rasterize_to_pixels`
  calls that CUDA kernel and nerfacc's CUDA scans), emulations written here from gsplat 1.5.3's CUDA sources.
  That checks our side of every call (camera conventions, radii, tile lists and their order, pixel centres,
  conics layout, the alpha / termination rules, depth channel, weight sums, pixel counts) and the gradients.
- Registration: without gsplat the module imports and 'auto' on CUDA keeps the reference, with one warning.
"""

from __future__ import annotations

import importlib
import importlib.util
import math
import subprocess
import sys
import warnings
from collections.abc import Callable

import pytest
import torch
from test_rasterizer import assert_close_rel, assert_matches_reference, brute_force, random_scene, run_with_grads
from torch import Tensor

from uw3dgs.cameras import Camera
from uw3dgs.render import RasterSettings, Splats, gsplat_backend, rasterize
from uw3dgs.render.gsplat_backend import Kernels, rasterize_gsplat
from uw3dgs.render.projection import project_gaussians
from uw3dgs.render.rasterize import BACKENDS, select_backend
from uw3dgs.render.reference import rasterize_reference
from uw3dgs.render.sh import eval_sh

F64 = torch.float64
F32 = torch.float32
HAS_GSPLAT = importlib.util.find_spec("gsplat") is not None
HAS_CUDA = torch.cuda.is_available()

needs_gsplat = pytest.mark.skipif(
    not HAS_GSPLAT, reason="gsplat glue tests skipped: gsplat is not installed (pip install uw3dgs[cuda])"
)
needs_cuda_and_gsplat = pytest.mark.skipif(
    not (HAS_CUDA and HAS_GSPLAT),
    reason="gsplat CUDA parity tests skipped: needs CUDA and gsplat (pip install uw3dgs[cuda]); "
    f"CUDA available: {HAS_CUDA}, gsplat installed: {HAS_GSPLAT}",
)

WIDTH, HEIGHT = 64, 48
GSPLAT_ALPHA = dict(alpha_max=0.999, alpha_min=1.0 / 255.0, transmittance_min=1e-4)
"""Settings equal to the constants compiled into gsplat's kernels: the backend's fused path."""


# --- PyTorch stand-ins for gsplat's CUDA rasterization kernels (gsplat 1.5.3, RasterizeToIndices3DGS.cu and
# RasterizeToPixels3DGSFwd.cu): one thread per pixel walks its tile's list front to back;
# sigma = 0.5 (a dx^2 + c dy^2) + b dx dy with (dx, dy) = mean - pixel centre; alpha = min(0.999, opacity
# exp(-sigma)); skipped if sigma < 0 or alpha < 1/255; the pixel stops at the first Gaussian with
# T (1 - alpha) <= 1e-4, which is not blended.


def _tile_blend(means2d, conics, opacities, width, height, tile_size, offsets, flatten_ids, start_t,
                batches=(0, None)):  # fmt: skip
    """Per tile: pixel ids [P], Gaussian ids [K], alpha [P, K] (autograd), blended [P, K]; only the Gaussians of
    batches [first, last) of tile_size^2 of each list."""
    tiles_y, tiles_x = offsets.shape[-2:]
    n = means2d.shape[-2]
    bounds = offsets.flatten().tolist() + [len(flatten_ids)]
    first, last = batches
    for tile in range(tiles_y * tiles_x):
        lo = bounds[tile] + first * tile_size**2
        hi = bounds[tile + 1] if last is None else min(bounds[tile + 1], bounds[tile] + last * tile_size**2)
        ids = flatten_ids[lo : max(lo, hi)].long() % n
        ty, tx = divmod(tile, tiles_x)
        ys = torch.arange(ty * tile_size, min((ty + 1) * tile_size, height))
        xs = torch.arange(tx * tile_size, min((tx + 1) * tile_size, width))
        pix = (ys[:, None] * width + xs[None, :]).flatten()
        px = (pix % width).float() + 0.5
        py = (pix // width).float() + 0.5
        mean, conic, opac = means2d[0, ids], conics[0, ids], opacities[0, ids]
        dx = mean[None, :, 0] - px[:, None]
        dy = mean[None, :, 1] - py[:, None]
        sigma = 0.5 * (conic[:, 0] * dx * dx + conic[:, 2] * dy * dy) + conic[:, 1] * dx * dy
        alpha = torch.clamp(opac * torch.exp(-sigma), max=0.999)
        with torch.no_grad():
            skip = (sigma < 0) | (alpha < 1.0 / 255.0)
            t_after = start_t[pix][:, None] * torch.cumprod(torch.where(skip, 1.0, 1.0 - alpha), dim=1)
            done = torch.cumsum((~skip & (t_after <= 1e-4)).int(), dim=1) > 0
            blended = ~skip & ~done
        yield pix, ids, alpha, blended


@torch.no_grad()
def indices_in_range_torch(range_start, range_end, transmittances, means2d, conics, opacities, width, height,
                           tile_size, offsets, flatten_ids):  # fmt: skip
    """rasterize_to_indices_in_range: (gaussian_ids, pixel_ids, image_ids), by pixel, front to back."""
    assert transmittances.dtype == means2d.dtype == conics.dtype == opacities.dtype == torch.float32
    assert transmittances.shape == (1, height, width) and 0 <= range_start < range_end
    gauss, pixel = [], []
    start_t = transmittances.reshape(-1)
    for pix, ids, _alpha, blended in _tile_blend(means2d, conics, opacities, width, height, tile_size, offsets,
                                                 flatten_ids, start_t, (range_start, range_end)):  # fmt: skip
        p, k = blended.nonzero(as_tuple=True)
        gauss.append(ids[k])
        pixel.append(pix[p])
    gauss, pixel = torch.cat(gauss), torch.cat(pixel)
    order = torch.argsort(pixel, stable=True)
    return gauss[order], pixel[order], torch.zeros_like(pixel)


def rasterize_to_pixels_torch(means2d, conics, colors, opacities, width, height, tile_size, offsets, flatten_ids,
                              backgrounds=None):  # fmt: skip
    """rasterize_to_pixels (differentiable): [1, H, W, C] colours and [1, H, W, 1] alpha = 1 - T."""
    assert backgrounds is None
    assert means2d.dtype == conics.dtype == colors.dtype == opacities.dtype == torch.float32
    start_t = torch.ones(height * width)
    pixels, renders, alphas = [], [], []
    for pix, ids, alpha, blended in _tile_blend(means2d, conics, opacities, width, height, tile_size, offsets,
                                                flatten_ids, start_t):  # fmt: skip
        a = torch.where(blended, alpha, torch.zeros_like(alpha))
        t = torch.cumprod(1.0 - a, dim=1)
        before = torch.cat([torch.ones_like(t[:, :1]), t[:, :-1]], dim=1)
        renders.append((a * before) @ colors[0, ids])
        alphas.append(1.0 - t[:, -1] if t.shape[1] else torch.zeros(len(pix)))
        pixels.append(pix)
    order = torch.cat(pixels)
    inverse = torch.empty_like(order)
    inverse[order] = torch.arange(len(order))
    render = torch.cat(renders)[inverse].view(1, height, width, -1)
    return render, torch.cat(alphas)[inverse].view(1, height, width, 1)


class Counted:
    """Wraps a kernel and counts its calls."""

    def __init__(self, fn: Callable):
        self.fn, self.calls = fn, 0

    def __call__(self, *args, **kwargs):
        self.calls += 1
        return self.fn(*args, **kwargs)


def torch_kernels() -> Kernels:
    from gsplat.cuda import _torch_impl

    return Kernels(
        isect_tiles=Counted(_torch_impl._isect_tiles),
        isect_offset_encode=_torch_impl._isect_offset_encode,
        rasterize_to_indices_in_range=Counted(indices_in_range_torch),
        rasterize_to_pixels=Counted(rasterize_to_pixels_torch),
    )


# --- comparison helpers


# --- glue tests on CPU tensors (gsplat's kernels swapped for PyTorch versions)

KNOBS = RasterSettings(tile_size=32, eps2d=0.1, alpha_min=0.02, alpha_max=0.95, transmittance_min=1e-2,
                       near_plane=0.5, far_plane=6.0)  # fmt: skip
EXACT_CASES = [
    pytest.param(0, 300, 3, RasterSettings(), F64, id="default-f64"),
    pytest.param(1, 300, 4, RasterSettings(), F32, id="default-f32-4ch"),
    pytest.param(2, 200, 3, RasterSettings(tile_size=8), F64, id="tile8-f64"),
    pytest.param(3, 300, 3, KNOBS, F64, id="all-knobs-f64"),
    pytest.param(4, 200, 3, RasterSettings(**GSPLAT_ALPHA), F64, id="gsplat-constants-f64"),
]


@needs_gsplat
@pytest.mark.parametrize("seed,n,channels,settings,dtype", EXACT_CASES)
def test_glue_exact_path_matches_reference(seed, n, channels, settings, dtype) -> None:
    """Settings gsplat's fused kernel cannot do (alpha_max 0.99, other knobs, float64): candidate pairs from
    rasterize_to_indices_in_range, compositing in PyTorch. Every output and input gradient match the reference;
    the scenes have Gaussians behind the camera, off-screen, tiny and huge, alpha_max clamping and termination."""
    scene = random_scene(seed, n, WIDTH, HEIGHT, channels=channels)
    kernels = torch_kernels()
    out, grads = run_with_grads(rasterize_gsplat, scene, dtype, settings, kernels=kernels)
    ref, ref_grads = run_with_grads(rasterize_reference, scene, dtype, settings)
    assert_matches_reference(out, grads, ref, ref_grads, dtype)
    assert kernels.rasterize_to_pixels.calls == 0 and kernels.rasterize_to_indices_in_range.calls >= 1
    assert (ref.radii == 0).any() and (ref.depths < 0).any() and ref.alpha.max() > 0.9
    assert brute_force(scene, settings).terminated_pixels > 0


@needs_gsplat
def test_glue_exact_path_in_steps(monkeypatch: pytest.MonkeyPatch) -> None:
    """Long tile lists walked one batch at a time: terminated pixels drop out, transmittance carries over."""
    monkeypatch.setattr(gsplat_backend, "BATCHES_PER_STEP", 1)
    scene = random_scene(8, 400, WIDTH, HEIGHT)
    settings = RasterSettings(tile_size=4)  # batches of 16 Gaussians
    kernels = torch_kernels()
    for dtype in (F64, F32):
        out, grads = run_with_grads(rasterize_gsplat, scene, dtype, settings, kernels=kernels)
        ref, ref_grads = run_with_grads(rasterize_reference, scene, dtype, settings)
        assert_matches_reference(out, grads, ref, ref_grads, dtype)
    assert kernels.rasterize_to_indices_in_range.calls > 4


@needs_gsplat
@pytest.mark.parametrize("seed,n,tile_size", [(0, 300, 16), (1, 300, 8), (5, 150, 64)])
def test_glue_fused_path_matches_reference(seed: int, n: int, tile_size: int) -> None:
    """alpha_max 0.999, alpha_min 1/255, transmittance_min 1e-4, float32: gsplat's rasterize_to_pixels renders,
    rasterize_to_indices_in_range (starting T = 1) gives the pixel counts and weight sums."""
    scene = random_scene(seed, n, WIDTH, HEIGHT, channels=3)
    settings = RasterSettings(tile_size=tile_size, **GSPLAT_ALPHA)
    kernels = torch_kernels()
    out, grads = run_with_grads(rasterize_gsplat, scene, F32, settings, kernels=kernels)
    ref, ref_grads = run_with_grads(rasterize_reference, scene, F32, settings)
    assert_matches_reference(out, grads, ref, ref_grads, F32)
    assert kernels.rasterize_to_pixels.calls == 1 and kernels.rasterize_to_indices_in_range.calls == 1
    assert ref.alpha.max() > 0.99 and brute_force(scene, settings).terminated_pixels > 0


@needs_gsplat
def test_glue_sh_colour_gradients() -> None:
    """Colours from degree-3 SH (as fields/gaussians.py makes them): gradients of the SH coefficients match."""
    scene = random_scene(6, 250, WIDTH, HEIGHT)
    gen = torch.Generator().manual_seed(3)
    sh = torch.randn(250, 16, 3, generator=gen, dtype=F64) * 0.3
    settings = RasterSettings()

    def sh_grad(fn, **kwargs) -> tuple[Tensor, Tensor]:
        coeffs = sh.clone().requires_grad_(True)
        dirs = torch.nn.functional.normalize(scene.means - scene.camera.center, dim=-1)
        colours = (eval_sh(3, coeffs, dirs) + 0.5).clamp_min(0.0)
        out = fn(Splats(scene.means, scene.quats, scene.scales, scene.opacities, colours), scene.camera, settings,
                 **kwargs)
        (out.render * torch.linspace(-1, 1, 3, dtype=F64)).sum().backward()
        return out.render, coeffs.grad

    render, grad = sh_grad(rasterize_gsplat, kernels=torch_kernels())
    ref_render, ref_grad = sh_grad(rasterize_reference)
    assert ref_grad.abs().sum() > 0
    assert_close_rel(render.detach(), ref_render.detach(), F64, "render")
    assert_close_rel(grad, ref_grad, F64, "grad sh")


@needs_gsplat
@pytest.mark.parametrize("case", ["empty", "all-culled"])
def test_glue_empty_views(case: str) -> None:
    scene = random_scene(5, 0 if case == "empty" else 20, WIDTH, HEIGHT)
    if case == "all-culled":
        scene.opacities.fill_(1e-3)  # below alpha_min everywhere: every radius is 0
    for settings, dtype in ((RasterSettings(), F64), (RasterSettings(**GSPLAT_ALPHA), F32)):
        leaves = [t.to(dtype).clone().requires_grad_(True) for t in scene.inputs()]
        cam = scene.camera
        cam = Camera(cam.viewmat.to(dtype), cam.K.to(dtype), WIDTH, HEIGHT)
        out = rasterize_gsplat(Splats(*leaves), cam, settings, kernels=torch_kernels())
        ref = rasterize_reference(Splats(*[t.detach() for t in leaves]), cam, settings)
        assert out.render.shape == (HEIGHT, WIDTH, 3) and out.alpha.shape == out.depth.shape == (HEIGHT, WIDTH)
        torch.testing.assert_close(out.render.detach(), ref.render)
        assert torch.equal(out.pixel_count, ref.pixel_count) and torch.equal(out.radii, ref.radii)
        (out.render.sum() + out.alpha.sum()).backward()  # the graph exists even with nothing drawn


@needs_gsplat
def test_projection_conventions_match_gsplat() -> None:
    """gsplat's own PyTorch projection agrees with ours on viewmat, K, (w, x, y, z) quaternions, eps2d, depths and
    conics layout when the principal point is the image centre; with an off-centre principal point its
    asymmetric Jacobian clamp gives other conics for Gaussians beyond 1.3 half-fields of view, which is why the
    backend projects with our own code."""
    from gsplat.cuda._torch_impl import _fully_fused_projection, _quat_scale_to_covar_preci

    scene = random_scene(3, 400, WIDTH, HEIGHT)
    covars, _ = _quat_scale_to_covar_preci(scene.quats, scene.scales, compute_preci=False)
    settings = RasterSettings()

    def both(K: Tensor):
        _, means2d, depths, conics, _ = _fully_fused_projection(
            scene.means, covars, scene.camera.viewmat[None], K[None], WIDTH, HEIGHT, settings.eps2d,
            settings.near_plane, settings.far_plane,
        )  # fmt: skip
        ours = project_gaussians(*scene.inputs()[:4], scene.camera.viewmat, K, WIDTH, HEIGHT, settings)
        return (means2d[0], depths[0], conics[0]), ours

    centred = scene.camera.K.clone()
    centred[0, 2], centred[1, 2] = WIDTH / 2, HEIGHT / 2
    (means2d, depths, conics), ours = both(centred)
    front = ours.depths > settings.near_plane
    torch.testing.assert_close(depths, ours.depths)
    torch.testing.assert_close(means2d[front], ours.means2d[front])
    torch.testing.assert_close(conics[front], ours.conics[front], rtol=1e-9, atol=1e-12)

    (means2d, depths, conics), ours = both(scene.camera.K)  # cx = W/2 + 1.3, cy = H/2 - 0.7
    torch.testing.assert_close(means2d[front], ours.means2d[front])
    differs = ~torch.isclose(conics, ours.conics, rtol=1e-9, atol=1e-12).all(-1) & front
    # they differ only where one of the two clamps is active: ours at +-0.65 W/fx (x/z), gsplat's at
    # -(cx/fx + 0.15 W/fx) and (W - cx)/fx + 0.15 W/fx
    beyond = torch.zeros_like(front)
    for axis, size in ((0, WIDTH), (1, HEIGHT)):
        f, c = scene.camera.K[axis, axis].item(), scene.camera.K[axis, 2].item()
        limit = min(0.65 * size / f, (size - c) / f + 0.15 * size / f, c / f + 0.15 * size / f)
        beyond |= ((ours.means2d[:, axis] - c) / f).abs() > limit
    assert differs.any() and not (differs & ~beyond).any()
    assert (differs & ours.valid).any()  # and some of them are drawn


@needs_gsplat
def test_sh_conventions_match_gsplat() -> None:
    """gsplat's SH (coefficient layout [N, K, 3], basis order and signs) is ours, up to degree 3."""
    from gsplat.cuda._torch_impl import _spherical_harmonics

    gen = torch.Generator().manual_seed(0)
    dirs = torch.nn.functional.normalize(torch.randn(50, 3, generator=gen, dtype=F64), dim=-1)
    coeffs = torch.randn(50, 16, 3, generator=gen, dtype=F64)
    for degree in range(4):
        torch.testing.assert_close(_spherical_harmonics(degree, dirs, coeffs), eval_sh(degree, coeffs, dirs))


# --- registration, laziness, fallbacks (no GPU needed)


def _python(code: str) -> str:
    result = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert result.returncode == 0, result.stderr[-3000:]
    return result.stdout


def test_without_gsplat_module_imports_and_auto_keeps_the_reference() -> None:
    """gsplat made unimportable: uw3dgs imports, 'gsplat' is not registered, 'auto' on CUDA resolves to 'torch'
    with exactly one warning naming the install command, and CPU is unaffected."""
    out = _python(
        "import sys, warnings, importlib\n"
        "sys.modules['gsplat'] = None  # import gsplat raises ImportError, find_spec returns None\n"
        "import torch\n"
        "import uw3dgs.render.gsplat_backend as gb\n"
        "r = importlib.import_module('uw3dgs.render.rasterize')\n"
        "assert not gb.gsplat_installed() and 'gsplat' not in r.BACKENDS, sorted(r.BACKENDS)\n"
        "with warnings.catch_warnings(record=True) as caught:\n"
        "    warnings.simplefilter('always')\n"
        "    picks = [r.select_backend('auto', torch.device(d)) for d in ('cuda', 'cuda', 'cpu')]\n"
        "msgs = [str(w.message) for w in caught]\n"
        "assert picks == ['torch', 'torch', 'cpu'], picks\n"
        "assert len(msgs) == 1 and 'pip install uw3dgs[cuda]' in msgs[0], msgs\n"
        "print('ok')\n"
    )
    assert out.strip() == "ok"


@needs_gsplat
def test_registered_for_cuda_only_and_imported_lazily() -> None:
    out = _python(
        "import sys, importlib, torch\n"
        "r = importlib.import_module('uw3dgs.render.rasterize')\n"
        "b = r.BACKENDS['gsplat']\n"
        "assert b.devices == frozenset({'cuda'}) and b.priority > r.BACKENDS['torch'].priority\n"
        "assert r.select_backend('auto', torch.device('cuda')) == 'gsplat'\n"
        "assert r.select_backend('auto', torch.device('cpu')) == 'cpu'\n"
        "assert 'gsplat' not in sys.modules, 'gsplat must be imported on first use only'\n"
        "print('ok')\n"
    )
    assert out.strip() == "ok"


def test_selection_warns_once_when_gsplat_is_missing(monkeypatch: pytest.MonkeyPatch) -> None:
    rasterize_module = importlib.import_module("uw3dgs.render.rasterize")
    monkeypatch.setattr(rasterize_module, "BACKENDS", {k: v for k, v in BACKENDS.items() if k != "gsplat"})
    monkeypatch.setattr(gsplat_backend, "_state", {})
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        assert rasterize_module.select_backend("auto", torch.device("cuda")) == "torch"
        assert rasterize_module.select_backend("auto", torch.device("cuda")) == "torch"
        assert rasterize_module.select_backend("torch", torch.device("cuda")) == "torch"
        assert rasterize_module.select_backend("auto", torch.device("cpu")) == "cpu"
    messages = [str(w.message) for w in caught if issubclass(w.category, RuntimeWarning)]
    assert len(messages) == 1 and "pip install uw3dgs[cuda]" in messages[0]


def test_failed_kernel_load_warns_once(monkeypatch: pytest.MonkeyPatch) -> None:
    def fail():
        raise RuntimeError("no CUDA toolkit")

    monkeypatch.setattr(gsplat_backend, "_state", {})
    monkeypatch.setattr(gsplat_backend, "_import_cuda_kernels", fail)
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        assert gsplat_backend.load_kernels() is None
        assert gsplat_backend.load_kernels() is None
    messages = [str(w.message) for w in caught if issubclass(w.category, RuntimeWarning)]
    assert len(messages) == 1 and "no CUDA toolkit" in messages[0] and "falling back" in messages[0]


def test_clear_errors() -> None:
    scene = random_scene(7, 10)
    cam = scene.camera
    with pytest.raises(ValueError, match="runs on CUDA tensors"):
        rasterize_gsplat(scene.splats(), cam, RasterSettings())
    with pytest.raises(ValueError, match="alpha_min"):
        rasterize_gsplat(scene.splats(), cam, RasterSettings(alpha_min=0.0))
    if "gsplat" in BACKENDS:
        with pytest.raises(ValueError, match="does not run on cpu"):
            rasterize(scene.splats(), cam, RasterSettings(backend="gsplat"))


def test_fused_path_conditions() -> None:
    fused = gsplat_backend.fused_path_applies
    assert fused(RasterSettings(**GSPLAT_ALPHA), F32, 3)
    assert not fused(RasterSettings(), F32, 3)  # alpha_max 0.99: gsplat's kernels clamp at 0.999
    assert not fused(RasterSettings(**GSPLAT_ALPHA), F64, 3)
    assert not fused(RasterSettings(**{**GSPLAT_ALPHA, "transmittance_min": 1e-3}), F32, 3)
    assert not fused(RasterSettings(**GSPLAT_ALPHA), F32, 513)


# --- CUDA parity with the real gsplat kernels (not run on machines without a GPU)

CUDA_SCENES = [(0, 300, 64, 48), (2, 2000, 97, 61), (6, 4000, 128, 96)]


@pytest.fixture(scope="module")
def cuda_kernels() -> Kernels:
    """gsplat's real CUDA functions (built on first use); a load failure fails the tests instead of letting the
    backend fall back to the reference, which would compare the reference with itself."""
    kernels = gsplat_backend.load_kernels()
    assert kernels is not None, f"gsplat is installed but its CUDA kernels did not load: {gsplat_backend._state}"
    return Kernels(
        isect_tiles=kernels.isect_tiles,
        isect_offset_encode=kernels.isect_offset_encode,
        rasterize_to_indices_in_range=Counted(kernels.rasterize_to_indices_in_range),
        rasterize_to_pixels=Counted(kernels.rasterize_to_pixels),
    )


@needs_cuda_and_gsplat
@pytest.mark.parametrize("path", ["exact", "fused"])
@pytest.mark.parametrize("seed,n,width,height", CUDA_SCENES)
def test_cuda_matches_reference(seed: int, n: int, width: int, height: int, path: str, cuda_kernels) -> None:
    """Outputs and gradients of means, quats, scales, opacities, features (and means2d) within 1e-4 relative of
    the reference on the same GPU, float32; the exact path (default settings) and the fused one."""
    scene = random_scene(seed, n, width, height, channels=4 if seed == 2 else 3)
    settings = RasterSettings(**GSPLAT_ALPHA) if path == "fused" else RasterSettings()
    fused_calls = cuda_kernels.rasterize_to_pixels.calls
    out, grads = run_with_grads(rasterize_gsplat, scene, F32, settings, device="cuda", kernels=cuda_kernels)
    ref, ref_grads = run_with_grads(rasterize_reference, scene, F32, settings, device="cuda")
    assert cuda_kernels.rasterize_to_pixels.calls - fused_calls == (1 if path == "fused" else 0)
    assert out.render.is_cuda and (ref.radii == 0).any() and (ref.depths < 0).any()
    if path == "exact":
        assert_matches_reference(out, grads, ref, ref_grads, F32)
        return
    # gsplat's kernels use __expf (fast math): a pair right at alpha_min or a pixel right at the termination
    # threshold can flip; allow a handful of such pixel-count differences, nothing else
    counts = (out.pixel_count - ref.pixel_count).abs().sum().item()
    assert counts <= max(2, 1e-4 * ref.pixel_count.sum().item()), counts
    out.pixel_count = ref.pixel_count
    assert_matches_reference(out, grads, ref, ref_grads, F32)


@needs_cuda_and_gsplat
def test_cuda_float64_exact_path(cuda_kernels) -> None:
    scene = random_scene(1, 500, 64, 48)
    out, grads = run_with_grads(rasterize_gsplat, scene, F64, RasterSettings(), device="cuda", kernels=cuda_kernels)
    ref, ref_grads = run_with_grads(rasterize_reference, scene, F64, RasterSettings(), device="cuda")
    assert_matches_reference(out, grads, ref, ref_grads, F64)


@needs_cuda_and_gsplat
def test_cuda_auto_picks_gsplat(cuda_kernels) -> None:
    """rasterize() with 'auto' on CUDA tensors goes through the registered 'gsplat' backend (default kernels)."""
    assert select_backend("auto", torch.device("cuda")) == "gsplat"
    scene = random_scene(9, 300, 64, 48)
    leaves = [t.float().cuda().requires_grad_(True) for t in scene.inputs()]
    cam = Camera(scene.camera.viewmat.float().cuda(), scene.camera.K.float().cuda(), 64, 48)
    out = rasterize(Splats(*leaves), cam)
    out.means2d.retain_grad()
    out.render.sum().backward()
    assert out.means2d.grad is not None and out.means2d.grad.abs().sum() > 0
    assert math.isfinite(out.render.sum().item())
    ref = rasterize_reference(Splats(*[t.detach() for t in leaves]), cam, RasterSettings())
    assert_close_rel(out.render.detach(), ref.render, F32, "render")
