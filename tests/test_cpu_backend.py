"""The compiled CPU backend ('cpu') against the torch reference: outputs, gradients, determinism, fallback."""

from __future__ import annotations

import warnings

import pytest
import torch
from test_rasterizer import Scene, brute_force, random_scene
from torch import Tensor

from uw3dgs.cameras import Camera
from uw3dgs.render import RasterSettings, cpu_backend, rasterize
from uw3dgs.render.rasterize import BACKENDS, select_backend
from uw3dgs.render.reference import rasterize_reference

F64 = torch.float64


@pytest.fixture(scope="module", autouse=True)
def extension():
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        module = cpu_backend.load_extension()
    if module is None:
        pytest.skip(f"the C++ CPU rasterizer could not be built here: {cpu_backend._state.get('error')}")
    return module


def _run(fn, scene: Scene, dtype: torch.dtype, settings: RasterSettings, seed: int = 1):
    """Outputs and gradients of a random linear loss over render, alpha, depth (and means2d's grad)."""
    leaves = [t.to(dtype).clone().requires_grad_(True) for t in scene.inputs()]
    cam = scene.camera
    out = fn(*leaves, cam.viewmat.to(dtype), cam.K.to(dtype), cam.width, cam.height, settings)
    out.means2d.retain_grad()
    gen = torch.Generator().manual_seed(seed)
    loss = sum((t * torch.randn(t.shape, generator=gen, dtype=dtype)).sum() for t in (out.render, out.alpha, out.depth))
    loss.backward()
    grads = dict(zip(("means", "quats", "scales", "opacities", "features"), (t.grad for t in leaves), strict=True))
    grads["means2d"] = out.means2d.grad
    return out, grads


def _close(actual: Tensor, expected: Tensor, dtype: torch.dtype, name: str) -> None:
    """float64: 1e-9 relative; float32: 1e-4 relative, with an absolute floor of 1e-4 x the largest entry."""
    rel = 1e-9 if dtype == F64 else 1e-4
    scale = expected.abs().max().item() if expected.numel() else 0.0
    torch.testing.assert_close(actual, expected, rtol=rel, atol=rel * max(scale, 1e-12), msg=name)


SCENES = [(0, 60, 40, 30, 16), (1, 300, 40, 30, 8), (2, 2000, 97, 61, 16), (6, 4000, 128, 96, 16)]


@pytest.mark.parametrize("dtype", [F64, torch.float32], ids=["f64", "f32"])
@pytest.mark.parametrize("seed,n,width,height,tile", SCENES)
def test_matches_reference(seed: int, n: int, width: int, height: int, tile: int, dtype: torch.dtype) -> None:
    """Every output and the gradient of every input match the reference (scenes include Gaussians behind
    the camera, off-screen, sub-pixel and screen-filling, alpha_max clamping and early termination)."""
    scene = random_scene(seed, n, width, height, channels=4 if seed == 1 else 3)
    settings = RasterSettings(tile_size=tile)
    out, grads = _run(cpu_backend.rasterize_cpu, scene, dtype, settings)
    ref, ref_grads = _run(rasterize_reference, scene, dtype, settings)
    for name in ("render", "alpha", "depth", "means2d", "depths", "weight_sum"):
        got, want = getattr(out, name), getattr(ref, name)
        assert got.dtype == want.dtype and got.shape == want.shape, name
        _close(got.detach(), want.detach(), dtype, name)
    assert out.radii.dtype == out.pixel_count.dtype == torch.int32
    assert torch.equal(out.radii, ref.radii)
    assert torch.equal(out.pixel_count, ref.pixel_count)
    assert not out.weight_sum.requires_grad and not out.pixel_count.requires_grad
    for name, want in ref_grads.items():
        assert grads[name] is not None and want.abs().sum() > 0, name
        _close(grads[name], want, dtype, f"grad {name}")
    assert (ref.radii == 0).any() and (ref.depths < 0).any() and ref.alpha.max() > 0.9


def test_matches_brute_force_autograd() -> None:
    """Independent check: the brute-force float64 renderer and autograd through it (test_rasterizer)."""
    scene = random_scene(2, 300)
    settings = RasterSettings(tile_size=8)
    leaves = [t.clone().requires_grad_(True) for t in scene.inputs()]
    weights = torch.randn(30, 40, 5, dtype=F64, generator=torch.Generator().manual_seed(7))

    def loss(out) -> Tensor:
        return (torch.cat([out.render, out.alpha[..., None], out.depth[..., None]], dim=-1) * weights).sum()

    out = rasterize(*leaves, scene.camera, RasterSettings(tile_size=8, backend="cpu"))
    grads = torch.autograd.grad(loss(out), leaves)
    ref = brute_force(Scene(*leaves, camera=scene.camera), settings)
    assert ref.terminated_pixels > 0
    ref_grads = torch.autograd.grad(loss(ref), leaves)
    torch.testing.assert_close(out.render, ref.render, rtol=0, atol=1e-10)
    assert torch.equal(out.pixel_count.long(), ref.pixel_count)
    for g, r in zip(grads, ref_grads, strict=True):
        torch.testing.assert_close(g, r, rtol=1e-8, atol=1e-9)


def test_gradcheck_small_scene() -> None:
    scene = random_scene(7, 12, 12, 10)
    scene.opacities.clamp_(max=0.9)  # stay away from the alpha_max kink
    settings = RasterSettings(tile_size=8, backend="cpu")

    def render(*inputs: Tensor) -> tuple[Tensor, ...]:
        out = rasterize(*inputs, scene.camera, settings)
        return out.render, out.alpha, out.depth

    inputs = tuple(t.clone().requires_grad_(True) for t in scene.inputs())
    assert torch.autograd.gradcheck(render, inputs, eps=1e-6, atol=1e-6, rtol=1e-4)


def test_bitwise_deterministic_across_runs_and_threads() -> None:
    scene = random_scene(8, 3000, 96, 80)
    settings = RasterSettings()
    threads = torch.get_num_threads()
    runs = []
    try:
        for n_threads in (threads, threads, 1, max(2, threads)):
            torch.set_num_threads(n_threads)
            out, grads = _run(cpu_backend.rasterize_cpu, scene, torch.float32, settings)
            runs.append([out.render, out.alpha, out.depth, out.weight_sum, out.pixel_count, *grads.values()])
    finally:
        torch.set_num_threads(threads)
    for other in runs[1:]:
        for a, b in zip(runs[0], other, strict=True):
            assert torch.equal(a, b)


def test_means2d_grad_and_empty_scene() -> None:
    scene = random_scene(9, 50)
    leaves = [t.float().requires_grad_(True) for t in scene.inputs()]
    cam = Camera(scene.camera.viewmat.float(), scene.camera.K.float(), 40, 30)
    out = rasterize(*leaves, cam, RasterSettings(backend="cpu"))
    out.means2d.retain_grad()
    out.render.sum().backward()
    assert out.means2d.grad is not None and out.means2d.grad.abs().sum() > 0
    empty = random_scene(5, 0)
    out = rasterize(*empty.inputs(), empty.camera, RasterSettings(backend="cpu"))
    assert out.render.shape == (30, 40, 3) and out.alpha.abs().sum() == 0 and out.radii.shape == (0,)


def test_registered_and_torch_still_selectable() -> None:
    assert BACKENDS["cpu"].devices == frozenset({"cpu"})
    assert select_backend("torch", torch.device("cpu")) == "torch"
    assert select_backend("cpu", torch.device("cpu")) == "cpu"
    with pytest.raises(ValueError, match="does not run on cuda"):
        select_backend("cpu", torch.device("cuda"))


def test_failed_build_warns_once_and_falls_back(monkeypatch: pytest.MonkeyPatch) -> None:
    from torch.utils import cpp_extension

    def fail(*args, **kwargs):
        raise RuntimeError("no C++ compiler")

    monkeypatch.setattr(cpu_backend, "_state", {})
    monkeypatch.setattr(cpp_extension, "load", fail)
    scene = random_scene(10, 40)
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        out = rasterize(*scene.inputs(), scene.camera, RasterSettings(backend="cpu"))
        rasterize(*scene.inputs(), scene.camera, RasterSettings(backend="cpu"))
    messages = [str(w.message) for w in caught if issubclass(w.category, RuntimeWarning)]
    assert len(messages) == 1 and "no C++ compiler" in messages[0] and "falling back" in messages[0]
    ref = rasterize_reference(*scene.inputs(), scene.camera.viewmat, scene.camera.K, 40, 30, RasterSettings())
    assert torch.equal(out.render, ref.render)
