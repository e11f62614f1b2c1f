"""The torch reference rasterizer against an independent brute-force renderer, plus its helpers."""

from __future__ import annotations

import importlib
import math
from dataclasses import dataclass

import pytest
import torch
from torch import Tensor

from uw3dgs.cameras import Camera
from uw3dgs.fields.gaussians import GaussianField, GaussianFieldConfig
from uw3dgs.kernels import build as kernel_build
from uw3dgs.kernels.sh_colors import sh_colors
from uw3dgs.render import RasterSettings, Splats, rasterize
from uw3dgs.render.projection import project_gaussians
from uw3dgs.render.rasterize import BACKENDS, register_backend, select_backend
from uw3dgs.render.reference import rasterize_reference
from uw3dgs.render.sh import eval_sh, eval_sh_split, rgb_to_sh, sh_to_rgb

F64 = torch.float64


@dataclass
class Scene:
    means: Tensor
    quats: Tensor
    scales: Tensor
    opacities: Tensor
    features: Tensor
    camera: Camera

    def inputs(self) -> tuple[Tensor, ...]:
        return self.means, self.quats, self.scales, self.opacities, self.features

    def splats(self) -> Splats:
        return Splats(*self.inputs())


def run_with_grads(fn, scene: Scene, dtype: torch.dtype, settings: RasterSettings, device: str = "cpu",
                   seed: int = 1, **kwargs):  # fmt: skip
    """Outputs and gradients of a random linear loss over render, alpha, depth (and means2d's grad)."""
    leaves = [t.to(device, dtype).clone().requires_grad_(True) for t in scene.inputs()]
    cam = scene.camera
    cam = Camera(cam.viewmat.to(device, dtype), cam.K.to(device, dtype), cam.width, cam.height)
    out = fn(Splats(*leaves), cam, settings, **kwargs)
    out.means2d.retain_grad()
    gen = torch.Generator().manual_seed(seed)
    loss = sum((t * torch.randn(t.shape, generator=gen, dtype=dtype).to(device)).sum()
               for t in (out.render, out.alpha, out.depth))  # fmt: skip
    loss.backward()
    grads = dict(zip(("means", "quats", "scales", "opacities", "features"), (t.grad for t in leaves), strict=True))
    grads["means2d"] = out.means2d.grad
    return out, grads


def assert_close_rel(actual: Tensor, expected: Tensor, dtype: torch.dtype, name: str) -> None:
    """float64: 1e-9 relative; float32: 1e-4 relative, with an absolute floor of 1e-4 x the largest entry."""
    rel = 1e-9 if dtype == F64 else 1e-4
    scale = expected.abs().max().item() if expected.numel() else 0.0
    # msg as a callable keeps torch's report (how many entries, the largest errors) after the quantity's name
    torch.testing.assert_close(actual, expected, rtol=rel, atol=rel * max(scale, 1e-12),
                               msg=lambda detail: f"{name} (largest |expected| {scale:.3g}): {detail}")


def assert_matches_reference(out, grads, ref, ref_grads, dtype: torch.dtype) -> None:
    """Every output of a backend and every gradient equal the reference's (integers exactly)."""
    for name in ("render", "alpha", "depth", "means2d", "depths", "conics", "weight_sum"):
        got, want = getattr(out, name), getattr(ref, name)
        assert got.dtype == want.dtype and got.shape == want.shape, name
        assert_close_rel(got.detach(), want.detach(), dtype, name)
    assert out.radii.dtype == out.pixel_count.dtype == torch.int32
    assert torch.equal(out.radii, ref.radii)
    assert torch.equal(out.pixel_count, ref.pixel_count), (out.pixel_count - ref.pixel_count).abs().sum()
    assert not out.weight_sum.requires_grad and not out.pixel_count.requires_grad
    for name, want in ref_grads.items():
        assert grads[name] is not None and want.abs().sum() > 0, name
        assert_close_rel(grads[name], want, dtype, f"grad {name}")


def _rotation_from_quat(q: Tensor) -> Tensor:
    """R = (w^2 - |v|^2) I + 2 v v^T + 2 w [v]_x, written independently of the library's version."""
    q = q / q.norm(dim=-1, keepdim=True)
    w, v = q[:, :1, None], q[:, 1:]
    cross = torch.zeros(len(q), 3, 3, dtype=q.dtype)
    cross[:, 0, 1], cross[:, 0, 2], cross[:, 1, 2] = -v[:, 2], v[:, 1], -v[:, 0]
    cross = cross - cross.transpose(1, 2)
    eye = torch.eye(3, dtype=q.dtype)
    return (w * w - (v * v).sum(-1)[:, None, None]) * eye + 2 * v[:, :, None] * v[:, None, :] + 2 * w * cross


def _random_camera(gen: torch.Generator, width: int, height: int) -> Camera:
    rot, _ = torch.linalg.qr(torch.randn(3, 3, generator=gen, dtype=F64))
    rot = rot * torch.sign(torch.det(rot))
    viewmat = torch.eye(4, dtype=F64)
    viewmat[:3, :3] = rot
    viewmat[:3, 3] = torch.randn(3, generator=gen, dtype=F64)
    f = 0.8 * width
    K = torch.tensor([[f, 0, 0.5 * width + 1.3], [0, 1.1 * f, 0.5 * height - 0.7], [0, 0, 1]], dtype=F64)
    return Camera(viewmat=viewmat, K=K, width=width, height=height)


def random_scene(seed: int, n: int, width: int = 40, height: int = 30, channels: int = 3) -> Scene:
    """Gaussians in front of, behind and beside the camera, from sub-pixel to screen-filling."""
    gen = torch.Generator().manual_seed(seed)

    def uniform(lo: float, hi: float, *shape: int) -> Tensor:
        return lo + (hi - lo) * torch.rand(*shape, generator=gen, dtype=F64)

    camera = _random_camera(gen, width, height)
    z = uniform(-1.0, 8.0, n)  # about 1 in 9 behind the camera
    xy = uniform(-0.9, 0.9, n, 2) * z.abs()[:, None]  # some beyond the field of view
    p_cam = torch.cat([xy, z[:, None]], dim=1)
    rot, t = camera.viewmat[:3, :3], camera.viewmat[:3, 3]
    means = (p_cam - t) @ rot
    scales = torch.exp(uniform(math.log(3e-3), math.log(0.4), n, 3))
    scales[: n // 20] = uniform(1.0, 4.0, n // 20, 3)  # huge
    scales[n // 20 : n // 10] = uniform(1e-5, 1e-3, n // 10 - n // 20, 3)  # tiny
    opacities = uniform(0.0, 1.0, n)
    opacities[n // 10 : n // 5] = uniform(0.985, 1.0, n // 5 - n // 10)  # exercise the alpha_max clamp
    quats = torch.randn(n, 4, generator=gen, dtype=F64) * uniform(0.5, 2.0, n, 1)
    features = uniform(-1.0, 2.0, n, channels)
    return Scene(means, quats, scales, opacities, features, camera)


@dataclass
class BruteForce:
    render: Tensor
    alpha: Tensor
    depth: Tensor
    weight_sum: Tensor
    pixel_count: Tensor
    terminated_pixels: int


def brute_force(scene: Scene, settings: RasterSettings) -> BruteForce:
    """3DGS blending evaluated for every pixel and every Gaussian, one Gaussian at a time, globally sorted."""
    cam = scene.camera
    fx, fy, cx, cy = cam.K[0, 0], cam.K[1, 1], cam.K[0, 2], cam.K[1, 2]
    rot, t = cam.viewmat[:3, :3], cam.viewmat[:3, 3]
    p = scene.means @ rot.T + t
    x, y, z = p.unbind(-1)

    lim_x, lim_y = 1.3 * cam.width / (2 * fx), 1.3 * cam.height / (2 * fy)
    tx = torch.clamp(x / z, -lim_x, lim_x) * z
    ty = torch.clamp(y / z, -lim_y, lim_y) * z
    J = torch.zeros(len(p), 2, 3, dtype=p.dtype)
    J[:, 0, 0], J[:, 0, 2] = fx / z, -fx * tx / z**2
    J[:, 1, 1], J[:, 1, 2] = fy / z, -fy * ty / z**2
    R = _rotation_from_quat(scene.quats)
    sigma = R @ torch.diag_embed(scene.scales**2) @ R.transpose(1, 2)
    cov2d = J @ rot @ sigma @ rot.T @ J.transpose(1, 2) + settings.eps2d * torch.eye(2, dtype=p.dtype)
    conic = torch.linalg.inv(cov2d)
    mean2d = torch.stack([fx * x / z + cx, fy * y / z + cy], dim=-1)

    v, u = torch.meshgrid(torch.arange(cam.height), torch.arange(cam.width), indexing="ij")
    pix = torch.stack([u.flatten(), v.flatten()], dim=-1).to(p.dtype) + 0.5
    T = torch.ones(len(pix), dtype=p.dtype)
    done = torch.zeros(len(pix), dtype=torch.bool)
    render = torch.zeros(len(pix), scene.features.shape[1], dtype=p.dtype)
    alpha_img = torch.zeros(len(pix), dtype=p.dtype)
    depth_img = torch.zeros(len(pix), dtype=p.dtype)
    weight_sum = torch.zeros(len(p), dtype=p.dtype)
    pixel_count = torch.zeros(len(p), dtype=torch.int64)
    in_range = (z >= settings.near_plane) & (z <= settings.far_plane)
    for i in torch.argsort(z.detach(), stable=True).tolist():
        if not in_range[i]:
            continue
        d = pix - mean2d[i]
        power = -0.5 * (conic[i, 0, 0] * d[:, 0] ** 2 + conic[i, 1, 1] * d[:, 1] ** 2)
        power = power - conic[i, 0, 1] * d[:, 0] * d[:, 1]
        alpha = torch.clamp(scene.opacities[i] * torch.exp(power), max=settings.alpha_max)
        skip = (power > 0) | (alpha < settings.alpha_min) | done
        t_next = T * (1 - alpha)
        stop = ~skip & (t_next < settings.transmittance_min)
        done = done | stop
        blend = ~skip & ~stop
        w = torch.where(blend, alpha * T, torch.zeros_like(T))
        render = render + w[:, None] * scene.features[i]
        alpha_img = alpha_img + w
        depth_img = depth_img + w * z[i]
        weight_sum[i] = w.sum().detach()
        pixel_count[i] = int(blend.sum())
        T = torch.where(blend, t_next, T)
    shape = (cam.height, cam.width)
    return BruteForce(
        render=render.reshape(*shape, -1),
        alpha=alpha_img.reshape(shape),
        depth=depth_img.reshape(shape),
        weight_sum=weight_sum,
        pixel_count=pixel_count,
        terminated_pixels=int(done.sum()),
    )


@pytest.mark.parametrize("tile_size", [16, 8])
@pytest.mark.parametrize("seed,n", [(0, 60), (1, 150), (2, 300)])
def test_reference_matches_brute_force(seed: int, n: int, tile_size: int) -> None:
    scene = random_scene(seed, n, channels=4 if seed == 1 else 3)
    settings = RasterSettings(backend="torch", tile_size=tile_size)
    out = rasterize(scene.splats(), scene.camera, settings)
    ref = brute_force(scene, settings)
    assert out.render.shape == (30, 40, scene.features.shape[1])
    assert out.alpha.shape == out.depth.shape == (30, 40)
    for name in ("render", "alpha", "depth", "weight_sum"):
        torch.testing.assert_close(getattr(out, name), getattr(ref, name), rtol=0, atol=1e-10, msg=name)
    assert torch.equal(out.pixel_count.long(), ref.pixel_count)
    assert ref.alpha.max() > 0.9 and ref.pixel_count.sum() > 0


def test_brute_force_scenes_cover_the_edge_cases() -> None:
    """The scenes above do hit culling, off-screen centres, huge footprints and early termination."""
    scene = random_scene(2, 300)
    settings = RasterSettings(backend="torch")
    proj = project_gaussians(*scene.inputs()[:4], scene.camera.viewmat, scene.camera.K, 40, 30, settings)
    assert (proj.depths < 0).any() and (proj.radii == 0).any() and (proj.radii > 20).any()
    x, y = proj.means2d[proj.valid].unbind(-1)
    assert ((x < 0) | (x > 40) | (y < 0) | (y > 30)).any()  # visible although centred off-screen
    assert brute_force(scene, settings).terminated_pixels > 0


def test_gradients_match_brute_force_autograd() -> None:
    """Custom backward == autograd through the brute-force renderer, termination and clamps included."""
    scene = random_scene(2, 300)
    settings = RasterSettings(backend="torch", tile_size=8)
    leaves = [t.clone().requires_grad_(True) for t in scene.inputs()]
    weights = torch.randn(30, 40, 5, dtype=F64, generator=torch.Generator().manual_seed(7))

    def loss(out) -> Tensor:
        stacked = torch.cat([out.render, out.alpha[..., None], out.depth[..., None]], dim=-1)
        return (stacked * weights).sum()

    grads = torch.autograd.grad(loss(rasterize(Splats(*leaves), scene.camera, settings)), leaves)
    ref = brute_force(Scene(*leaves, camera=scene.camera), settings)
    assert ref.terminated_pixels > 0
    ref_grads = torch.autograd.grad(loss(ref), leaves)
    for name, g, r in zip(("means", "quats", "scales", "opacities", "features"), grads, ref_grads, strict=True):
        torch.testing.assert_close(g, r, rtol=1e-8, atol=1e-9, msg=name)


def _tiny_scene() -> Scene:
    """Three overlapping Gaussians with moderate opacities: smooth, no clamping, no termination."""
    means = torch.tensor([[0.1, -0.05, 2.0], [-0.2, 0.1, 2.5], [0.25, 0.15, 3.0]], dtype=F64)
    gen = torch.Generator().manual_seed(11)
    quats = torch.randn(3, 4, generator=gen, dtype=F64)
    scales = torch.tensor([[0.15, 0.08, 0.1], [0.1, 0.2, 0.05], [0.2, 0.12, 0.3]], dtype=F64)
    opacities = torch.tensor([0.5, 0.6, 0.4], dtype=F64)
    features = torch.rand(3, 2, generator=gen, dtype=F64)
    K = torch.tensor([[10.0, 0, 6.2], [0, 11.0, 4.9], [0, 0, 1]], dtype=F64)
    camera = Camera(viewmat=torch.eye(4, dtype=F64), K=K, width=12, height=10)
    return Scene(means, quats, scales, opacities, features, camera)


def test_gradcheck_tiny_scene() -> None:
    scene = _tiny_scene()
    settings = RasterSettings(backend="torch", tile_size=8)

    def render(*inputs: Tensor) -> tuple[Tensor, ...]:
        out = rasterize(Splats(*inputs), scene.camera, settings)
        return out.render, out.alpha, out.depth

    inputs = tuple(t.clone().requires_grad_(True) for t in scene.inputs())
    assert torch.autograd.gradcheck(render, inputs, eps=1e-6, atol=1e-7, rtol=1e-5)


def test_means2d_grad_is_populated() -> None:
    scene = _tiny_scene()
    leaves = [t.clone().requires_grad_(True) for t in scene.inputs()]
    out = rasterize(Splats(*leaves), scene.camera)
    out.means2d.retain_grad()
    out.render.sum().backward()
    assert out.means2d.grad is not None and out.means2d.grad.shape == (3, 2)
    assert out.means2d.grad.abs().sum() > 0
    assert out.weight_sum.requires_grad is False and out.pixel_count.requires_grad is False


def test_float32_matches_float64() -> None:
    scene = random_scene(4, 200)
    out64 = rasterize(scene.splats(), scene.camera)
    leaves = [t.float().requires_grad_(True) for t in scene.inputs()]
    cam32 = Camera(scene.camera.viewmat.float(), scene.camera.K.float(), 40, 30)
    out32 = rasterize(Splats(*leaves), cam32)
    out32.render.sum().backward()
    assert out32.render.dtype == torch.float32
    torch.testing.assert_close(out32.render.double(), out64.render, rtol=0, atol=2e-3)
    assert all(torch.isfinite(t.grad).all() for t in leaves)


def test_empty_scene_renders_nothing() -> None:
    scene = random_scene(5, 0)
    out = rasterize(scene.splats(), scene.camera)
    assert out.render.shape == (30, 40, 3) and out.alpha.abs().sum() == 0


def test_projection_matches_pinhole_and_ewa() -> None:
    scene = _tiny_scene()
    cam, settings = scene.camera, RasterSettings(backend="torch")
    proj = project_gaussians(*scene.inputs()[:4], cam.viewmat, cam.K, cam.width, cam.height, settings)
    x, y, z = scene.means.unbind(-1)  # viewmat is the identity
    expected = torch.stack([cam.K[0, 0] * x / z + cam.K[0, 2], cam.K[1, 1] * y / z + cam.K[1, 2]], dim=-1)
    torch.testing.assert_close(proj.means2d, expected)
    torch.testing.assert_close(proj.depths, z)

    # The 2D covariance is the 3D one pushed through the numerical Jacobian of the pinhole map.
    def pinhole(p: Tensor) -> Tensor:
        return torch.stack([cam.K[0, 0] * p[0] / p[2], cam.K[1, 1] * p[1] / p[2]])

    R = _rotation_from_quat(scene.quats)
    a, b, c = proj.conics.unbind(-1)
    for i in range(3):
        J = torch.autograd.functional.jacobian(pinhole, scene.means[i])
        sigma = R[i] @ torch.diag(scene.scales[i] ** 2) @ R[i].T
        cov2d = J @ sigma @ J.T + settings.eps2d * torch.eye(2, dtype=F64)
        conic = torch.stack([torch.stack([a[i], b[i]]), torch.stack([b[i], c[i]])])
        torch.testing.assert_close(torch.linalg.inv(conic), cov2d)
        extent = math.sqrt(2 * math.log(scene.opacities[i].item() / settings.alpha_min))
        assert proj.radii[i] == math.ceil(extent * math.sqrt(torch.linalg.eigvalsh(cov2d)[-1].item()))


def test_projection_of_an_axis_aligned_gaussian() -> None:
    K = torch.tensor([[100.0, 0, 50.0], [0, 80.0, 40.0], [0, 0, 1]])
    means = torch.tensor([[0.0, 0.0, 4.0]])
    scales = torch.tensor([[0.2, 0.1, 0.3]])
    quats = torch.tensor([[2.0, 0.0, 0.0, 0.0]])  # unnormalised identity
    settings = RasterSettings(backend="torch")
    proj = project_gaussians(means, quats, scales, torch.ones(1), torch.eye(4), K, 100, 80, settings)
    var_x, var_y = (100 * 0.2 / 4) ** 2 + 0.3, (80 * 0.1 / 4) ** 2 + 0.3
    torch.testing.assert_close(proj.conics, torch.tensor([[1 / var_x, 0.0, 1 / var_y]]))
    torch.testing.assert_close(proj.means2d, torch.tensor([[50.0, 40.0]]))


def test_projection_culls_behind_off_screen_and_faint() -> None:
    K = torch.tensor([[20.0, 0, 10.0], [0, 20.0, 10.0], [0, 0, 1]])
    means = torch.tensor([[0.0, 0.0, -1.0], [0.0, 0.0, 0.005], [30.0, 0.0, 2.0], [0.0, 0.0, 2.0], [0.0, 0, 2.0]])
    opacities = torch.tensor([0.9, 0.9, 0.9, 0.9, 0.003])
    quats = torch.tensor([[1.0, 0, 0, 0]]).repeat(5, 1)
    proj = project_gaussians(means, quats, torch.full((5, 3), 0.05), opacities, torch.eye(4), K, 20, 20,
                             RasterSettings(backend="torch"))  # fmt: skip
    assert proj.valid.tolist() == [False, False, False, True, False]
    assert (proj.radii[~proj.valid] == 0).all() and proj.radii.dtype == torch.int32


@pytest.mark.parametrize("backend", ["torch", "cpu"])
@pytest.mark.parametrize("dtype", [F64, torch.float32])
def test_reused_projection_renders_lower_opacities_exactly(backend: str, dtype: torch.dtype) -> None:
    """PAUP's masked render: the same view with the opacities scaled down (some below alpha_min, so culled by a
    fresh projection) gives the same render, opacity gradient and per-Gaussian weights with the full render's
    projection, and in the compiled backend its tile lists: bitwise there, to rounding in the reference (its tiles'
    padded Gaussian lists grow)."""
    if backend == "cpu" and not kernel_build.is_available():
        pytest.skip("the compiled backend does not build here")
    scene = random_scene(5, 400)
    settings = RasterSettings(backend=backend)
    means, quats, scales, opacities, features = (t.to(dtype) for t in scene.inputs())
    # recorded for a backward, as in training: the compiled backend then hands on its tile lists
    full = rasterize(Splats(means, quats, scales, opacities, features.clone().requires_grad_(True)), scene.camera,
                     settings)
    assert (full.tile_lists is not None) == (backend == "cpu")
    keep = torch.rand(len(means), generator=torch.Generator().manual_seed(0), dtype=dtype)
    keep[:50] = 1e-4  # opacity x keep < alpha_min
    weights = torch.randn(full.render.shape, generator=torch.Generator().manual_seed(1), dtype=dtype)

    def masked(**reuse) -> tuple[Tensor, ...]:
        scaled = keep.clone().requires_grad_(True)
        out = rasterize(Splats(means, quats, scales, opacities * scaled, features), scene.camera, settings, **reuse)
        (out.render * weights).sum().backward()
        return out.render.detach(), scaled.grad, out.weight_sum, out.pixel_count.to(dtype)

    fresh, reused = masked(), masked(projection=full)
    assert fresh[0].abs().sum() > 0 and fresh[1].abs().sum() > 0
    names = ("render", "grad opacities", "weight_sum", "pixel_count")
    for got, want, name in zip(reused, fresh, names, strict=True):
        if backend == "cpu":
            assert torch.equal(got, want), name
        else:
            assert_close_rel(got, want, dtype, name)
    with pytest.raises(ValueError, match="no gradient to means"):
        rasterize(Splats(means.clone().requires_grad_(True), quats, scales, opacities, features), scene.camera,
                  settings, projection=full)


def _sh_direct(l: int, m: int, d: Tensor) -> Tensor:
    """Real SH with the Condon-Shortley phase from associated Legendre polynomials."""
    theta, phi = torch.acos(d[:, 2]), torch.atan2(d[:, 1], d[:, 0])
    x, am = torch.cos(theta), abs(m)
    # P_l^|m| by the standard recurrences (Condon-Shortley phase included).
    p_mm = (-1) ** am * math.prod(range(1, 2 * am, 2)) * torch.sin(theta) ** am
    p_prev, p = p_mm, x * (2 * am + 1) * p_mm
    if l == am:
        p = p_mm
    for ll in range(am + 2, l + 1):
        p_prev, p = p, ((2 * ll - 1) * x * p - (ll + am - 1) * p_prev) / (ll - am)
    norm = math.sqrt((2 * l + 1) / (4 * math.pi) * math.factorial(l - am) / math.factorial(l + am))
    if m == 0:
        return norm * p
    trig = torch.cos(am * phi) if m > 0 else torch.sin(am * phi)
    return math.sqrt(2) * norm * trig * p


def test_eval_sh_matches_direct_formula() -> None:
    dirs = torch.nn.functional.normalize(torch.tensor([[0.3, -0.5, 0.8], [-0.7, 0.2, -0.1]], dtype=F64), dim=-1)
    for degree in range(4):
        for l in range(degree + 1):
            for m in range(-l, l + 1):
                sh = torch.zeros(2, 16, 3, dtype=F64)
                sh[:, l * l + l + m, 1] = 1.0
                value = eval_sh(degree, sh, dirs)
                torch.testing.assert_close(value[:, 1], _sh_direct(l, m, dirs), msg=f"l={l} m={m}")
                assert value[:, 0].abs().max() == 0


def test_eval_sh_gradients_match_finite_differences() -> None:
    generator = torch.Generator().manual_seed(3)
    for degree in range(4):
        dirs = torch.randn(4, 3, dtype=F64, generator=generator).requires_grad_()
        sh = torch.randn(4, 16, 3, dtype=F64, generator=generator).requires_grad_()
        # through the normalisation, as the Gaussians' colours take it (unit directions from free vectors)
        assert torch.autograd.gradcheck(
            lambda d, c, k=degree: eval_sh(k, c, torch.nn.functional.normalize(d, dim=-1)), (dirs, sh))


def sh_colour_case(dtype: torch.dtype, n: int = 3000, seed: int = 0):
    """Gaussians around a camera centre with random degree-3 coefficients; some colours clamp at 0."""
    g = torch.Generator().manual_seed(seed)
    means = torch.randn(n, 3, generator=g, dtype=dtype).requires_grad_()
    dc = (0.8 * torch.randn(n, 3, generator=g, dtype=dtype)).requires_grad_()
    rest = (0.3 * torch.randn(n, 15, 3, generator=g, dtype=dtype)).requires_grad_()
    return means, torch.tensor([0.3, -0.2, 0.1], dtype=dtype), dc, rest


def sh_colours_torch(means, center, dc, rest, degree):
    return (eval_sh_split(degree, dc, rest, torch.nn.functional.normalize(means - center, dim=-1)) + 0.5).clamp_min(0)


@pytest.mark.parametrize(("dtype", "tolerance"), [(torch.float64, 1e-13), (torch.float32, 1e-5)])
@pytest.mark.parametrize("degree", [0, 1, 2, 3])
def test_compiled_sh_colours_match_pytorch(dtype, tolerance, degree) -> None:
    """The kernel against GaussianField's PyTorch expression: colours and the gradients of means and coefficients
    (those above the degree get zero), relative to each tensor's largest value; Gaussians with no colour gradient
    (not seen in the view) get exact zeros, which the kernel writes without working them out."""
    means, center, dc, rest = sh_colour_case(dtype)
    weights = torch.randn(len(means), 3, generator=torch.Generator().manual_seed(1), dtype=dtype)
    weights[::3] = 0.0
    results = []
    for colours in (sh_colours_torch, sh_colors):
        for t in (means, dc, rest):
            t.grad = None
        out = colours(means, center, dc, rest, degree)
        (out * weights).sum().backward()
        results.append([out.detach()] + [torch.zeros_like(t) if t.grad is None else t.grad for t in (means, dc, rest)])
    assert bool((results[1][0] == 0).any())  # the clamp is exercised
    assert all(bool((g[::3] == 0).all()) for g in results[1][1:]) and bool((results[1][2][1::3] != 0).any())
    for a, b in zip(*results, strict=True):
        assert float((a - b).abs().max()) <= tolerance * max(float(b.abs().max()), 1e-30)


def test_compiled_sh_colours_gradients_against_finite_differences() -> None:
    means, center, dc, rest = sh_colour_case(torch.float64, n=6)
    with torch.no_grad():
        dc += 1.0  # away from the clamp's kink
    assert torch.autograd.gradcheck(lambda m, d, r: sh_colors(m, center, d, r, 3), (means, dc, rest))


def test_gaussian_field_colours_compiled_or_torch_agree() -> None:
    """`--model.kernels compiled` (default) and `torch` colour a field the same (float rounding)."""
    field = GaussianField(GaussianFieldConfig(), torch.randn(500, 3), torch.rand(500, 3))
    assert field.kernels == "compiled"
    with torch.no_grad():
        field.shN.normal_(std=0.2)
    field.set_step(10_000)
    center = torch.tensor([0.0, 0.0, -3.0])
    colours = []
    for kernels in ("compiled", "torch"):
        field.kernels = kernels
        colours.append(field.colors(center))
    torch.testing.assert_close(colours[0], colours[1], rtol=1e-5, atol=1e-6)


def test_sh_degree_zero_round_trip() -> None:
    rgb = torch.rand(5, 3)
    torch.testing.assert_close(sh_to_rgb(rgb_to_sh(rgb)), rgb)
    dirs = torch.nn.functional.normalize(torch.randn(5, 3), dim=-1)
    torch.testing.assert_close(eval_sh(0, rgb_to_sh(rgb)[:, None, :], dirs) + 0.5, rgb)
    with pytest.raises(ValueError):
        eval_sh(2, torch.zeros(5, 4, 3), dirs)


def test_backend_registry(monkeypatch: pytest.MonkeyPatch) -> None:
    # the compiled backend is the CPU default (tests/test_cpu_backend.py checks it against this reference)
    assert select_backend("auto", torch.device("cpu")) == "cpu"
    assert select_backend("auto", torch.device("cuda")) == ("gsplat" if "gsplat" in BACKENDS else "torch")
    assert BACKENDS["torch"].fn is rasterize_reference
    scene = _tiny_scene()
    with pytest.raises(ValueError, match="torch"):
        rasterize(scene.splats(), scene.camera, RasterSettings(backend="no-such-backend"))

    # The package re-exports the function `rasterize`, which shadows the module's name as an attribute.
    monkeypatch.setattr(importlib.import_module("uw3dgs.render.rasterize"), "BACKENDS", dict(BACKENDS))
    calls = []

    def fake(*args):
        calls.append(args)
        return rasterize_reference(*args)

    register_backend("fast", fake, devices=("cpu",), priority=100)
    register_backend("gpu-only", fake, devices=("cuda",), priority=200)
    assert select_backend("auto", torch.device("cpu")) == "fast"
    rasterize(scene.splats(), scene.camera)
    assert len(calls) == 1
    with pytest.raises(ValueError, match="does not run on cpu"):
        select_backend("gpu-only", torch.device("cpu"))
