"""Image metrics and losses against hand computations and an independent brute-force SSIM."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from scipy.ndimage import correlate

from uw3dgs.kernels import build as kernel_build
from uw3dgs.methods.uw3dgs.depth_consistency import depth_consistency
from uw3dgs.metrics.depth import range_abs_rel
from uw3dgs.metrics.image import MSE_FLOOR, dssim_loss, l1_loss, psnr, ssim


def reference_ssim(pred: np.ndarray, gt: np.ndarray) -> float:
    """Float64 SSIM of one [H, W, C] pair, written from the definition with an explicit 2D window."""
    radius, sigma = 5, 1.5
    window = np.zeros((2 * radius + 1, 2 * radius + 1))
    for i in range(-radius, radius + 1):
        for j in range(-radius, radius + 1):
            window[i + radius, j + radius] = np.exp(-(i * i + j * j) / (2 * sigma**2))
    window /= window.sum()

    def blur(channel: np.ndarray) -> np.ndarray:
        return correlate(channel, window, mode="constant", cval=0.0)

    c1, c2 = 0.01**2, 0.03**2
    maps = []
    for c in range(pred.shape[-1]):
        x, y = pred[..., c], gt[..., c]
        mu_x, mu_y = blur(x), blur(y)
        var_x = blur(x * x) - mu_x**2
        var_y = blur(y * y) - mu_y**2
        cov = blur(x * y) - mu_x * mu_y
        maps.append(
            ((2 * mu_x * mu_y + c1) * (2 * cov + c2)) / ((mu_x**2 + mu_y**2 + c1) * (var_x + var_y + c2))
        )
    return float(np.mean(maps))


def random_pair(shape: tuple[int, ...], noise: float, seed: int = 0, dtype=torch.float64):
    gen = torch.Generator().manual_seed(seed)
    gt = torch.rand(shape, generator=gen, dtype=dtype)
    pred = (gt + noise * torch.randn(shape, generator=gen, dtype=dtype)).clamp(0, 1)
    return pred, gt


def test_psnr_matches_hand_computation_per_image():
    pred, gt = random_pair((3, 7, 9, 3), noise=0.05)
    expected = [
        10 * np.log10(1.0 / np.mean((p - g) ** 2)) for p, g in zip(pred.numpy(), gt.numpy(), strict=True)
    ]
    values = psnr(pred, gt)
    assert values.shape == (3,)
    np.testing.assert_allclose(values.numpy(), expected, rtol=1e-12)
    assert psnr(pred[1], gt[1]).shape == ()
    assert psnr(pred[1], gt[1]).item() == pytest.approx(expected[1], rel=1e-12)


@pytest.mark.parametrize(("offset", "expected_db"), [(0.1, 20.0), (0.01, 40.0), (0.5, 6.0206)])
def test_psnr_of_a_constant_offset(offset, expected_db):
    gt = torch.full((8, 8, 3), 0.25, dtype=torch.float64)
    assert psnr(gt + offset, gt).item() == pytest.approx(expected_db, abs=1e-4)


def test_masked_psnr_counts_only_the_masked_pixels():
    pred, gt = random_pair((2, 6, 8, 3), noise=0.05)
    mask = torch.rand(2, 6, 8, generator=torch.Generator().manual_seed(3)) > 0.4
    expected = [10 * np.log10(1.0 / np.mean((p - g)[m] ** 2))
                for p, g, m in zip(pred.numpy(), gt.numpy(), mask.numpy(), strict=True)]
    np.testing.assert_allclose(psnr(pred, gt, mask).numpy(), expected, rtol=1e-12)
    assert psnr(pred[0], gt[0], torch.ones(6, 8, dtype=torch.bool)).item() == pytest.approx(psnr(pred[0], gt[0]).item())
    pred[0][~mask[0]] = 1 - gt[0][~mask[0]]  # errors outside the mask change nothing
    np.testing.assert_allclose(psnr(pred, gt, mask)[0].item(), expected[0], rtol=1e-12)
    with pytest.raises(ValueError, match="empty mask"):
        psnr(pred[0], gt[0], torch.zeros(6, 8, dtype=torch.bool))
    with pytest.raises(ValueError, match="mask shape"):
        psnr(pred[0], gt[0], torch.ones(6, 9, dtype=torch.bool))


def test_psnr_of_identical_images_is_finite():
    img = torch.rand(5, 5, 3)
    assert psnr(img, img).item() == pytest.approx(-10 * np.log10(MSE_FLOOR))


def test_metrics_reject_mismatched_shapes():
    with pytest.raises(ValueError, match="shapes differ"):
        psnr(torch.rand(4, 4, 3), torch.rand(4, 5, 3))
    with pytest.raises(ValueError, match="H, W, C"):
        ssim(torch.rand(4, 3), torch.rand(4, 3))


@pytest.mark.parametrize("shape", [(2, 17, 23, 3), (1, 6, 4, 3), (1, 30, 12, 1)])
def test_ssim_matches_brute_force_reference(shape):
    pred, gt = random_pair(shape, noise=0.1, seed=shape[1])
    values = ssim(pred, gt)
    expected = [reference_ssim(p, g) for p, g in zip(pred.numpy(), gt.numpy(), strict=True)]
    np.testing.assert_allclose(values.numpy(), expected, rtol=0, atol=1e-12)
    # float32, the training dtype, stays close to the float64 reference.
    values32 = ssim(pred.float(), gt.float())
    np.testing.assert_allclose(values32.numpy(), expected, rtol=0, atol=2e-5)


def test_ssim_unbatched_returns_a_scalar():
    pred, gt = random_pair((10, 11, 3), noise=0.1)
    value = ssim(pred, gt)
    assert value.shape == ()
    assert value.item() == pytest.approx(reference_ssim(pred.numpy(), gt.numpy()), abs=1e-12)


def test_ssim_identity_and_symmetry():
    pred, gt = random_pair((2, 16, 16, 3), noise=0.1)
    torch.testing.assert_close(ssim(gt, gt), torch.ones(2, dtype=torch.float64))
    torch.testing.assert_close(ssim(pred, gt), ssim(gt, pred), rtol=0, atol=1e-14)


def test_ssim_decreases_with_noise():
    values = [ssim(*random_pair((24, 24, 3), noise=s)).item() for s in (0.0, 0.02, 0.05, 0.1, 0.2)]
    assert values[0] == pytest.approx(1.0)
    assert all(a > b for a, b in zip(values, values[1:], strict=False))


@pytest.fixture
def single_thread():
    """gradcheck runs hundreds of tiny forward passes; thread hand-offs would dominate on a busy machine."""
    previous = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(previous)


def test_ssim_gradient_matches_finite_differences(single_thread):
    pred, gt = random_pair((1, 6, 7, 3), noise=0.2)
    pred.requires_grad_(True)
    gt.requires_grad_(True)
    assert torch.autograd.gradcheck(ssim, (pred, gt), eps=1e-6, atol=1e-5)


compiled_ssim = pytest.mark.skipif(not kernel_build.is_available(), reason="the compiled backend does not build here")


@compiled_ssim
@pytest.mark.parametrize("shape", [(2, 17, 23, 3), (1, 6, 4, 3), (1, 30, 12, 1)])
def test_compiled_ssim_matches_brute_force_reference(shape):
    pred, gt = random_pair(shape, noise=0.1, seed=shape[1])
    expected = [reference_ssim(p, g) for p, g in zip(pred.numpy(), gt.numpy(), strict=True)]
    np.testing.assert_allclose(ssim(pred, gt, "compiled").numpy(), expected, rtol=0, atol=1e-12)
    np.testing.assert_allclose(ssim(pred.float(), gt.float(), "compiled").numpy(), expected, rtol=0, atol=2e-5)
    assert ssim(pred[0], gt[0], "compiled").shape == ()


@compiled_ssim
@pytest.mark.parametrize(("dtype", "tolerance"), [(torch.float64, 1e-12), (torch.float32, 1e-5)])
def test_compiled_ssim_gradient_matches_pytorch(dtype, tolerance):
    pred, gt = random_pair((2, 19, 26, 3), noise=0.15, seed=4)
    grads = {}
    for kernel in ("torch", "compiled"):
        p = pred.to(dtype).requires_grad_(True)
        dssim_loss(p, gt.to(dtype), kernel).backward()
        grads[kernel] = p.grad
    scale = grads["torch"].abs().max()
    assert scale > 0
    torch.testing.assert_close(grads["compiled"], grads["torch"], rtol=tolerance, atol=tolerance * scale)


@compiled_ssim
def test_compiled_ssim_gradient_matches_finite_differences(single_thread):
    pred, gt = random_pair((1, 6, 7, 3), noise=0.2)
    pred.requires_grad_(True)
    assert torch.autograd.gradcheck(lambda p: ssim(p, gt, "compiled"), (pred,), eps=1e-6, atol=1e-5)


@compiled_ssim
def test_compiled_ssim_is_bitwise_the_same_on_one_and_two_threads():
    pred, gt = random_pair((1, 40, 33, 3), noise=0.1)
    results = []
    threads = torch.get_num_threads()
    try:
        for n in (1, 2):
            torch.set_num_threads(n)
            p = pred.float().requires_grad_(True)
            value = ssim(p, gt.float(), "compiled")
            value.sum().backward()
            results.append((value.detach(), p.grad))
    finally:
        torch.set_num_threads(threads)
    assert all(torch.equal(a, b) for a, b in zip(*results, strict=True))


def test_compiled_ssim_leaves_a_gt_that_needs_a_gradient_to_pytorch():
    pred, gt = random_pair((1, 9, 9, 3), noise=0.1)
    gt.requires_grad_(True)
    ssim(pred, gt, "compiled").backward()
    assert gt.grad is not None and gt.grad.abs().sum() > 0


def test_losses():
    pred, gt = random_pair((2, 9, 9, 3), noise=0.1)
    pred.requires_grad_(True)
    assert dssim_loss(pred, gt).item() == pytest.approx(1.0 - ssim(pred, gt).mean().item())
    assert l1_loss(pred, gt).item() == pytest.approx((pred - gt).abs().mean().item())
    assert dssim_loss(gt, gt).item() == pytest.approx(0.0, abs=1e-12)
    (dssim_loss(pred, gt) + l1_loss(pred, gt)).backward()
    assert pred.grad is not None and torch.isfinite(pred.grad).all()


def test_range_abs_rel_counts_covered_surface_pixels_only():
    truth = torch.tensor([[2.0, 4.0], [float("inf"), 5.0]])
    pred = torch.tensor([[2.2, 3.0], [9.0, 100.0]])
    alpha = torch.tensor([[1.0, 0.6], [1.0, 0.5]])  # (1, 1) half covered: its range is not a surface
    # (0, 0): 0.2 / 2, (0, 1): 1 / 4; open water (1, 0) and the half-covered pixel are left out
    assert range_abs_rel(pred, alpha, truth) == pytest.approx((0.1 + 0.25) / 2, abs=1e-7)
    assert range_abs_rel(pred, torch.zeros_like(alpha), truth) is None


def _depth_consistency_scene(seed: int, n: int, dtype: torch.dtype = torch.float64):
    """Gaussians in view and out of it (radius 0, centres off the image), several on one pixel, and one whose
    rendered range equals its own distance (|.|'s kink); ranges [H, W] = 12 x 10."""
    gen = torch.Generator().manual_seed(seed)
    means = torch.randn(n, 3, generator=gen, dtype=dtype) * 2 + torch.tensor([0.0, 0.0, 6.0], dtype=dtype)
    means2d = torch.rand(n, 2, generator=gen, dtype=dtype) * torch.tensor([14.0, 12.0], dtype=dtype) - 1.0
    means2d[: n // 4] = means2d[n // 4: 2 * (n // 4)]  # shared pixels
    radii = (torch.rand(n, generator=gen) > 0.2).to(torch.int32) * 3
    ranges = torch.rand(10, 12, generator=gen, dtype=dtype) * 4 + 4
    center = torch.tensor([0.1, -0.2, 0.3], dtype=dtype)
    means2d[0], radii[0] = torch.tensor([5.5, 4.5], dtype=dtype), 3
    ranges[4, 5] = (means[0] - center).norm()
    weights = torch.rand(n, generator=gen, dtype=dtype) * 0.3 + 0.7
    return ranges, means, means2d, radii, center, weights


@pytest.mark.parametrize("weighted", [False, True])
def test_depth_consistency_matches_its_definition(weighted):
    ranges, means, means2d, radii, center, weights = _depth_consistency_scene(0, 40)
    weights = weights if weighted else None
    terms, rendered = [], []
    for i in range(len(means)):  # the definition, one Gaussian at a time
        x, y = int(np.floor(float(means2d[i, 0]))), int(np.floor(float(means2d[i, 1])))
        if radii[i] > 0 and 0 <= x < 12 and 0 <= y < 10:
            rendered.append(float(ranges[y, x]))
            terms.append((float(ranges[y, x]), float((means[i] - center).norm()), 1.0 if weights is None
                          else float(weights[i])))
    scale = sorted(rendered)[(len(rendered) - 1) // 2]  # the lower median
    expected = sum(w * abs(r - z) / scale for r, z, w in terms) / len(terms)
    for kernel in ("torch", "compiled"):
        if kernel == "compiled" and not kernel_build.is_available():
            continue
        got = depth_consistency(ranges, means, means2d, radii, center, weights, kernel)
        assert float(got) == pytest.approx(expected, rel=1e-12), kernel


@pytest.mark.parametrize(("dtype", "tolerance"), [(torch.float64, 1e-12), (torch.float32, 1e-5)])
@pytest.mark.parametrize("weighted", [False, True])
def test_compiled_depth_consistency_matches_pytorch(dtype, tolerance, weighted):
    """Loss and gradients (ranges, means) of the compiled L_z against the PyTorch path in float64, relative to each
    tensor's largest value, with several Gaussians on a pixel and the kink of |.| at 0."""
    if not kernel_build.is_available():
        pytest.skip("the compiled CPU backend does not build here")
    scene = _depth_consistency_scene(1, 5000)

    def run(kernel: str, dtype: torch.dtype) -> list[torch.Tensor]:
        ranges, means, means2d, radii, center, weights = (t.to(dtype) if t.is_floating_point() else t
                                                          for t in scene)
        ranges, means = ranges.clone().requires_grad_(), means.clone().requires_grad_()
        loss = depth_consistency(ranges, means, means2d, radii, center, weights if weighted else None, kernel)
        (3.0 * loss).backward()
        return [loss.detach(), ranges.grad, means.grad]

    reference = run("torch", torch.float64)
    for got, want in zip(run("compiled", dtype), reference, strict=True):
        assert float((got.double() - want).abs().max()) <= tolerance * float(want.abs().max())
    assert reference[1].abs().sum() > 0 and reference[2].abs().sum() > 0


def test_depth_consistency_without_a_centre_in_the_image_is_zero_with_a_graph():
    ranges, means, means2d, radii, center, _ = _depth_consistency_scene(2, 10)
    means2d = means2d + 100.0
    for kernel in ("torch", "compiled"):
        r = ranges.clone().requires_grad_()
        loss = depth_consistency(r, means, means2d, radii, center, None, kernel)
        loss.backward()
        assert float(loss.detach()) == 0.0 and float(r.grad.abs().sum()) == 0.0
