"""uw3dgs's own image operations against the libraries that define the same operation, where the conventions meet:
PSNR and SSIM against scikit-image's `metrics` and kornia's SSIM, the SSIM blur against kornia's filter, CIELab
against scikit-image's `color`, the area downscaling against scikit-image's `transform`."""

from __future__ import annotations

import kornia
import numpy as np
import pytest
import torch
from skimage.color import rgb2lab
from skimage.metrics import peak_signal_noise_ratio, structural_similarity
from skimage.transform import downscale_local_mean

from uw3dgs.data.downscale import area_downscale
from uw3dgs.kernels import build as kernel_build
from uw3dgs.metrics.image import SSIM_SIGMA, SSIM_WINDOW, _gaussian_blur, psnr, ssim, ssim_map
from uw3dgs.metrics.underwater_quality import cielab

RADIUS = SSIM_WINDOW // 2


def pair(height: int, width: int, seed: int = 0, frame: int = 0) -> tuple[torch.Tensor, torch.Tensor]:
    """A float64 [H, W, 3] pair in [0, 1], gt and a noisy prediction; with `frame`, both 0 within that many pixels
    of every border."""
    g = torch.Generator().manual_seed(seed)
    gt = torch.rand(height, width, 3, generator=g, dtype=torch.float64)
    pred = (gt + 0.1 * torch.randn(height, width, 3, generator=g, dtype=torch.float64)).clamp(0, 1)
    if frame:
        inside = torch.zeros(height, width, 1, dtype=torch.float64)
        inside[frame:-frame, frame:-frame] = 1
        gt, pred = gt * inside, pred * inside
    return pred, gt


def skimage_ssim(pred: torch.Tensor, gt: torch.Tensor) -> tuple[float, np.ndarray]:
    """scikit-image's SSIM in 3DGS's form (Gaussian window, sigma 1.5, population statistics, dynamic range 1):
    (its mean, which leaves out a border of the window's radius; its full map [H, W, C], reflect-padded)."""
    return structural_similarity(gt.numpy(), pred.numpy(), data_range=1.0, channel_axis=-1, gaussian_weights=True,
                                 sigma=SSIM_SIGMA, use_sample_covariance=False, full=True)


def test_psnr_is_scikit_images():
    pred, gt = pair(17, 23)
    assert float(psnr(pred, gt)) == pytest.approx(peak_signal_noise_ratio(gt.numpy(), pred.numpy(), data_range=1.0),
                                                  rel=1e-12)


def test_ssim_away_from_the_border_is_scikit_images_and_kornias():
    # scikit-image and kornia pad by reflection, 3DGS (and uw3dgs) with zeros: the maps agree where the window
    # stays inside the image; scikit-image's mean is over exactly those pixels
    pred, gt = pair(24, 31)
    ours = ssim_map(pred[None], gt[None])[0]  # [C, H, W]
    inner = ours[:, RADIUS:-RADIUS, RADIUS:-RADIUS]
    mean, _ = skimage_ssim(pred, gt)
    assert float(inner.mean()) == pytest.approx(mean, rel=1e-12)
    theirs = kornia.metrics.ssim(pred.permute(2, 0, 1)[None], gt.permute(2, 0, 1)[None], SSIM_WINDOW, max_val=1.0,
                                 padding="valid")[0]
    assert torch.allclose(inner, theirs, rtol=0, atol=1e-9)  # kornia adds 1e-12 to the denominator
    # at the border the conventions differ, and so do the maps
    assert not torch.allclose(ours[:, 0], torch.from_numpy(skimage_ssim(pred, gt)[1]).permute(2, 0, 1)[:, 0])


@pytest.mark.parametrize("kernel", ["torch", "compiled"])
def test_ssim_of_images_in_a_black_frame_is_scikit_images_full_map(kernel):
    # within a black frame at least the window's radius wide, reflecting reads zeros as zero padding does: the
    # conventions meet over the whole image (scikit-image's full map, not its cropped mean)
    if kernel == "compiled" and not kernel_build.is_available():
        pytest.skip("the compiled CPU kernels are not built here")
    pred, gt = pair(30, 26, seed=1, frame=RADIUS)
    _, full = skimage_ssim(pred, gt)
    assert float(ssim(pred, gt, kernel)) == pytest.approx(float(full.mean()), rel=1e-10)


def test_the_ssim_blur_is_kornias_zero_padded_separable_filter():
    images = torch.rand(2, 19, 27, 5, dtype=torch.float64)
    taps = kornia.filters.get_gaussian_kernel1d(SSIM_WINDOW, SSIM_SIGMA, dtype=torch.float64)
    theirs = kornia.filters.filter2d_separable(images.permute(0, 3, 1, 2), taps, taps, border_type="constant")
    assert torch.allclose(_gaussian_blur(images), theirs, rtol=0, atol=1e-14)


def test_cielab_is_scikit_images():
    g = torch.Generator().manual_seed(2)
    image = torch.rand(9, 11, 3, generator=g, dtype=torch.float64)
    image[0, :3] = torch.tensor([[0.0, 0.0, 0.0], [1.0, 1.0, 1.0], [0.02, 0.01, 0.03]], dtype=torch.float64)
    assert np.allclose(cielab(image).numpy(), rgb2lab(image.numpy()), rtol=0, atol=2e-3)
    assert np.allclose(cielab(image.float()).numpy(), rgb2lab(image.numpy()), rtol=0, atol=2e-3)


@pytest.mark.parametrize(("height", "width", "factor"), [(12, 18, 3), (13, 20, 4)])
def test_area_downscale_is_scikit_images_local_mean(height, width, factor):
    # scikit-image pads a partial last block with zeros, uw3dgs drops it: they agree on the whole blocks
    image = torch.rand(height, width, 3, dtype=torch.float64)
    ours = area_downscale(image, factor)
    theirs = downscale_local_mean(image.numpy(), (factor, factor, 1))
    assert np.allclose(ours.numpy(), theirs[: height // factor, : width // factor], rtol=0, atol=1e-14)


def test_tensorf_plane_tv_is_kornias_total_variation_squared_where_they_meet():
    """TensoRF's TVLoss squares the neighbours' differences, kornia's `total_variation` takes their absolute value
    (another operation, so the plane TV stays ours). On a 0/1 plane |d| = d^2, and on a square plane both directions
    share one normaliser: ours = 2 kornia_sum / (R (H - 1) W)."""
    from uw3dgs.fields.tensorf import total_variation

    plane = (torch.rand(1, 3, 9, 9, generator=torch.Generator().manual_seed(0)) > 0.5).double()
    expected = 2 * kornia.losses.total_variation(plane, reduction="sum").sum() / (3 * 8 * 9)
    torch.testing.assert_close(total_variation(plane), expected, rtol=1e-12, atol=0)
    assert not torch.allclose(total_variation(plane * 0.5), 2 * kornia.losses.total_variation(
        plane * 0.5, reduction="sum").sum() / (3 * 8 * 9))  # elsewhere they differ: squares against absolutes


def test_seasplat_depth_smoothness_is_kornias_where_the_image_only_brightens():
    """SeaSplat's `SmoothDepthLoss` weights by e^(-dI) of the signed image difference, kornia's
    `inverse_depth_smoothness_loss` by e^(-|dI|) (another operation, so ours stays): on an image that brightens to
    the right and downwards they agree, with the depth in place of the inverse depth."""
    from uw3dgs.methods.seasplat_losses import edge_aware_depth_smoothness

    g = torch.Generator().manual_seed(1)
    image = (torch.rand(12, 10, 3, generator=g, dtype=torch.float64) * 0.05).cumsum(0).cumsum(1)
    depth = torch.rand(12, 10, generator=g, dtype=torch.float64) * 5
    reference = kornia.losses.inverse_depth_smoothness_loss(depth[None, None], image.permute(2, 0, 1)[None])
    torch.testing.assert_close(edge_aware_depth_smoothness(image, depth), reference, rtol=1e-12, atol=0)
    darker = image.flip(0)  # a darkening edge: the signed weight lets the depth jump more
    assert edge_aware_depth_smoothness(darker, depth) > kornia.losses.inverse_depth_smoothness_loss(
        depth[None, None], darker.permute(2, 0, 1)[None])
