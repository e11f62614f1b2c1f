"""The compiled CPU backend ('cpu') against the torch reference: outputs, gradients, determinism, fallback."""

from __future__ import annotations

import dataclasses
import os
import socket
import subprocess
import sys
import threading
import time
import warnings
from pathlib import Path

import pytest
import torch
from test_rasterizer import Scene, assert_matches_reference, brute_force, random_scene, run_with_grads
from torch import Tensor

from uw3dgs.cameras import Camera
from uw3dgs.kernels import build as kernel_build
from uw3dgs.render import RasterSettings, Splats, cpu_backend, masked_l1, rasterize
from uw3dgs.render.rasterize import BACKENDS, select_backend
from uw3dgs.render.reference import rasterize_reference

F64 = torch.float64


@pytest.fixture(scope="module", autouse=True)
def extension():
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        module = kernel_build.load_extension()
    if module is None:
        pytest.skip(f"the C++ CPU rasterizer could not be built here: {kernel_build._state.get('error')}")
    return module


SCENES = [(0, 60, 40, 30, 16), (1, 300, 40, 30, 8), (2, 2000, 97, 61, 16), (6, 4000, 128, 96, 16)]


@pytest.mark.parametrize("dtype", [F64, torch.float32], ids=["f64", "f32"])
@pytest.mark.parametrize("seed,n,width,height,tile", SCENES)
def test_matches_reference(seed: int, n: int, width: int, height: int, tile: int, dtype: torch.dtype) -> None:
    """Every output and the gradient of every input match the reference (scenes include Gaussians behind
    the camera, off-screen, sub-pixel and screen-filling, alpha_max clamping and early termination)."""
    scene = random_scene(seed, n, width, height, channels=4 if seed == 1 else 3)
    settings = RasterSettings(tile_size=tile)
    out, grads = run_with_grads(cpu_backend.rasterize_cpu, scene, dtype, settings)
    ref, ref_grads = run_with_grads(rasterize_reference, scene, dtype, settings)
    assert_matches_reference(out, grads, ref, ref_grads, dtype)
    assert (ref.radii == 0).any() and (ref.depths < 0).any() and ref.alpha.max() > 0.9


def test_matches_brute_force_autograd() -> None:
    """Independent check: the brute-force float64 renderer and autograd through it (test_rasterizer)."""
    scene = random_scene(2, 300)
    settings = RasterSettings(tile_size=8)
    leaves = [t.clone().requires_grad_(True) for t in scene.inputs()]
    weights = torch.randn(30, 40, 5, dtype=F64, generator=torch.Generator().manual_seed(7))

    def loss(out) -> Tensor:
        return (torch.cat([out.render, out.alpha[..., None], out.depth[..., None]], dim=-1) * weights).sum()

    out = rasterize(Splats(*leaves), scene.camera, RasterSettings(tile_size=8, backend="cpu"))
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
        out = rasterize(Splats(*inputs), scene.camera, settings)
        return out.render, out.alpha, out.depth

    inputs = tuple(t.clone().requires_grad_(True) for t in scene.inputs())
    assert torch.autograd.gradcheck(render, inputs, eps=1e-6, atol=1e-6, rtol=1e-4)


def test_bitwise_deterministic_across_runs_and_threads() -> None:
    """Also the binning's depth sort and tile lists, made in blocks in parallel: enough visible Gaussians and
    pairs for more than one block at two threads (kParallelMin = 4,096 in cpu_rasterizer.cpp)."""
    scene = random_scene(8, 12000, 96, 80)
    settings = RasterSettings()
    threads = torch.get_num_threads()
    runs = []
    try:
        for n_threads in (threads, threads, 1, max(2, threads)):
            torch.set_num_threads(n_threads)
            out, grads = run_with_grads(cpu_backend.rasterize_cpu, scene, torch.float32, settings)
            runs.append([out.render, out.alpha, out.depth, out.weight_sum, out.pixel_count, out.radii,
                         *grads.values()])
    finally:
        torch.set_num_threads(threads)
    assert int((runs[0][5] > 0).sum()) > 4096  # Gaussians binned
    for other in runs[1:]:
        for a, b in zip(runs[0], other, strict=True):
            assert torch.equal(a, b)


def test_no_grad_forward_equals_recording_forward() -> None:
    """Under no_grad nothing is recorded for the backward; the outputs must not change by a single bit."""
    scene = random_scene(9, 3000, 96, 80)
    settings = RasterSettings()
    recorded, _ = run_with_grads(cpu_backend.rasterize_cpu, scene, torch.float32, settings)
    with torch.no_grad():
        cam = scene.camera
        cam32 = Camera(cam.viewmat.float(), cam.K.float(), cam.width, cam.height)
        plain = cpu_backend.rasterize_cpu(Splats(*(t.float() for t in scene.inputs())), cam32, settings)
    for name in ("render", "alpha", "depth", "means2d", "radii", "depths", "weight_sum", "pixel_count"):
        assert torch.equal(getattr(plain, name), getattr(recorded, name)), name


@pytest.mark.parametrize("dtype", [F64, torch.float32], ids=["f64", "f32"])
def test_opacity_only_backward_equals_full(dtype: torch.dtype) -> None:
    """With only the opacities requiring a gradient (PAUP's frozen render), the backward skips the rest; the
    opacities' gradient is the full backward's, bit for bit, and the reference's."""
    scene = random_scene(6, 3000, 96, 80)
    cam = Camera(scene.camera.viewmat.to(dtype), scene.camera.K.to(dtype), scene.camera.width, scene.camera.height)
    weights = torch.randn(80, 96, 3, dtype=dtype, generator=torch.Generator().manual_seed(3))

    def opacity_grad(backend, geometry: bool) -> Tensor:
        inputs = [t.to(dtype) for t in scene.inputs()]
        opacities = inputs[3].requires_grad_(True)
        if geometry:
            inputs[0].requires_grad_(True)
        out = backend(Splats(*inputs), cam, RasterSettings())
        (out.render * weights).sum().backward()
        return opacities.grad

    alone = opacity_grad(cpu_backend.rasterize_cpu, geometry=False)
    assert alone.abs().sum() > 0
    assert torch.equal(alone, opacity_grad(cpu_backend.rasterize_cpu, geometry=True))
    tol = 1e-10 if dtype == F64 else 1e-4
    torch.testing.assert_close(alone, opacity_grad(rasterize_reference, geometry=False), rtol=tol, atol=tol)


@pytest.mark.parametrize("dtype", [F64, torch.float32], ids=["f64", "f32"])
@pytest.mark.parametrize("reuse_lists", [True, False], ids=["lists", "binned"])
def test_masked_l1_equals_render_then_mean(dtype: torch.dtype, reuse_lists: bool) -> None:
    """PAUP's masked render and its L1 in one pass (`masked_l1`): the render is the compiled frozen render's with
    the full render's projection, bit for bit; the L1 and its gradient in the keep mask are autograd's through that
    render and the reference's, to rounding (the per-pixel gradient's 1 / (H W C) is applied after the sums, the
    L1 summed in double); the same bits at any thread count."""
    scene = random_scene(5, 3000, 96, 80)
    settings = RasterSettings(backend="cpu")
    means, quats, scales, opacities, features = (t.to(dtype) for t in scene.inputs())
    full = rasterize(Splats(means, quats, scales, opacities, features.clone().requires_grad_(True)), scene.camera,
                     settings)
    projection = full if reuse_lists else dataclasses.replace(full, tile_lists=None)
    target = full.render.detach()  # as in training: where no kept-less Gaussian reaches, the difference is 0
    keep = torch.rand(len(means), generator=torch.Generator().manual_seed(0), dtype=dtype)
    keep[keep > 0.05] = 1.0  # as in training, most Gaussians kept whole: some pixels the same in both renders
    keep[:50] = 1e-4  # opacity x keep < alpha_min

    def fused(target: Tensor = target) -> tuple[Tensor, Tensor, Tensor]:
        scaled = keep.clone().requires_grad_(True)
        image, l1 = masked_l1(projection, opacities * scaled, features, target, scene.camera, settings)
        (0.1 * l1).backward()
        return image, l1.detach(), scaled.grad

    def unfused(backend: str, target: Tensor = target) -> tuple[Tensor, Tensor, Tensor]:
        scaled = keep.clone().requires_grad_(True)
        out = rasterize(Splats(means, quats, scales, opacities * scaled, features), scene.camera,
                        RasterSettings(backend=backend), projection=full)
        l1 = (target - out.render).abs().mean()
        (0.1 * l1).backward()
        return out.render.detach(), l1.detach(), scaled.grad

    image, l1, grad = fused()
    render, want_l1, want_grad = unfused("cpu")
    assert torch.equal(image, render) and not image.requires_grad
    assert grad.abs().sum() > 0 and bool((target != image).any()) and bool((target == image).any())
    tol = 1e-12 if dtype == F64 else 1e-5
    torch.testing.assert_close(l1, want_l1, rtol=tol, atol=0)
    torch.testing.assert_close(grad, want_grad, rtol=tol, atol=tol * float(want_grad.abs().max()))
    # against the reference, a target away from both renders: where they agree with it exactly, their rounding
    # differences would pick different sides of |.|'s kink
    target = target + 0.1 * torch.randn(target.shape, generator=torch.Generator().manual_seed(1), dtype=dtype)
    _, l1, grad = fused(target)
    _, ref_l1, ref_grad = unfused("torch", target)
    tol = 1e-10 if dtype == F64 else 1e-4
    torch.testing.assert_close(l1, ref_l1, rtol=tol, atol=0)
    torch.testing.assert_close(grad, ref_grad, rtol=tol, atol=tol * float(ref_grad.abs().max()))
    threads = torch.get_num_threads()
    try:
        torch.set_num_threads(1 if threads > 1 else 2)
        again = fused(target)
    finally:
        torch.set_num_threads(threads)
    for a, b in zip(fused(target), again, strict=True):
        assert torch.equal(a, b)


def test_masked_l1_is_none_where_the_backend_has_no_fused_pass() -> None:
    scene = random_scene(5, 50)
    full = rasterize(scene.splats(), scene.camera, RasterSettings(backend="torch"))
    target = torch.zeros(30, 40, 3, dtype=F64)
    assert masked_l1(full, scene.opacities, scene.features, target, scene.camera, RasterSettings(backend="torch")) \
        is None


def test_means2d_grad_and_empty_scene() -> None:
    scene = random_scene(9, 50)
    leaves = [t.float().requires_grad_(True) for t in scene.inputs()]
    cam = Camera(scene.camera.viewmat.float(), scene.camera.K.float(), 40, 30)
    out = rasterize(Splats(*leaves), cam, RasterSettings(backend="cpu"))
    out.means2d.retain_grad()
    out.render.sum().backward()
    assert out.means2d.grad is not None and out.means2d.grad.abs().sum() > 0
    empty = random_scene(5, 0)
    out = rasterize(empty.splats(), empty.camera, RasterSettings(backend="cpu"))
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

    monkeypatch.setattr(kernel_build, "_state", {})
    monkeypatch.setattr(cpp_extension, "load", fail)
    scene = random_scene(10, 40)
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        out = rasterize(scene.splats(), scene.camera, RasterSettings(backend="cpu"))
        rasterize(scene.splats(), scene.camera, RasterSettings(backend="cpu"))
    messages = [str(w.message) for w in caught if issubclass(w.category, RuntimeWarning)]
    assert len(messages) == 1 and "no C++ compiler" in messages[0] and "falling back" in messages[0]
    ref = rasterize_reference(scene.splats(), scene.camera, RasterSettings())
    assert torch.equal(out.render, ref.render)


def test_each_checkout_builds_into_its_own_folder(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """Two checkouts of the same sources get two build folders (torch's build file names the sources' paths: a
    shared folder was rebuilt whenever the other checkout had run last); one checkout always the same folder, and
    a change of the sources a new one."""
    folders = []
    for checkout in ("a", "b"):
        copies = []
        for source in [*kernel_build.SOURCES, *kernel_build.HEADERS]:
            copy = tmp_path / checkout / source.name
            copy.parent.mkdir(parents=True, exist_ok=True)
            copy.write_bytes(source.read_bytes())
            copies.append(copy)
        monkeypatch.setattr(kernel_build, "SOURCES", copies[:len(kernel_build.SOURCES)])
        monkeypatch.setattr(kernel_build, "HEADERS", copies[len(kernel_build.SOURCES):])
        folders.append(kernel_build.build_directory())
        assert kernel_build.build_directory() == folders[-1]
    assert folders[0] != folders[1] and folders[0].parent == folders[1].parent
    copies[0].write_bytes(copies[0].read_bytes() + b"\n")
    assert kernel_build.build_directory() != folders[1]


def test_a_build_lock_left_by_a_killed_build_is_removed_and_a_live_one_waited_for(tmp_path: Path) -> None:
    """torch waits for ever on the `lock` of a build that was killed; the backend's own lock names its process, so
    a lock whose process is gone is removed (torch's with it), with a warning, and a live one is waited for."""
    dead = subprocess.Popen([sys.executable, "-c", "pass"])
    dead.wait()
    (tmp_path / "build.pid").write_text(f"{socket.gethostname()} {dead.pid}")
    (tmp_path / "lock").touch()
    with pytest.warns(RuntimeWarning, match="did not finish"), kernel_build.build_lock(tmp_path):
        assert (tmp_path / "build.pid").read_text() == f"{socket.gethostname()} {os.getpid()}"
        assert not (tmp_path / "lock").exists()
    assert not (tmp_path / "build.pid").exists()  # released
    # another host's lock: judged by its age
    (tmp_path / "build.pid").write_text("elsewhere 1")
    os.utime(tmp_path / "build.pid", (time.time() - 2 * kernel_build.STALE_LOCK_SECONDS,) * 2)
    with pytest.warns(RuntimeWarning, match="did not finish"), kernel_build.build_lock(tmp_path):
        pass
    # a live holder (this process, from another thread's point of view): waited for until it lets go
    holder = subprocess.Popen([sys.executable, "-c", "import time; time.sleep(0.5)"])
    (tmp_path / "build.pid").write_text(f"{socket.gethostname()} {holder.pid}")
    threading.Timer(0.3, lambda: (tmp_path / "build.pid").unlink()).start()
    start = time.perf_counter()
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        with kernel_build.build_lock(tmp_path, poll=0.05):
            pass
    assert time.perf_counter() - start >= 0.3
    holder.wait()
