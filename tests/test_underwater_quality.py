"""UCIQE and UIQM against hand computations on images with known statistics, against a float64 implementation
written from the papers' formulas (numpy, scikit-image's CIELab and scipy's Sobel: nothing shared with the code
under test), and their invariances."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
from scipy import ndimage
from skimage.color import rgb2lab

from uw3dgs.metrics.underwater_quality import (
    UCIQE_WEIGHTS,
    UIQM_WEIGHTS,
    uciqe,
    uicm,
    uiconm,
    uiqm,
    uism,
    underwater_quality,
)

# ---- the papers' formulas, float64, one image at a time --------------------------------------------------------------


def reference_uciqe(image: np.ndarray) -> float:
    lab = rgb2lab(image)
    lum, a, b = lab[..., 0].ravel() / 100, lab[..., 1].ravel() / 255, lab[..., 2].ravel() / 255
    chroma = np.sqrt(a * a + b * b)
    sigma_c = np.sqrt(np.mean((chroma - chroma.mean()) ** 2))
    ranked = np.sort(lum)
    con_l = ranked[int(0.99 * lum.size)] - ranked[int(0.01 * lum.size)]
    mu_s = np.mean([c / v if v > 0 else 0.0 for c, v in zip(chroma, lum, strict=True)])
    return UCIQE_WEIGHTS[0] * sigma_c + UCIQE_WEIGHTS[1] * con_l + UCIQE_WEIGHTS[2] * mu_s


def reference_trimmed_mean(values: np.ndarray) -> float:
    ranked = sorted(values.tolist())
    k = len(ranked)
    low, high = -(-k // 10), k // 10  # ceil(0.1 K), floor(0.1 K) in integers
    kept = ranked[low:k - high]
    return sum(kept) / len(kept)


def reference_uicm(image: np.ndarray) -> float:
    r, g, b = (255.0 * image.reshape(-1, 3)).T
    means, variances = [], []
    for opponent in (r - g, (r + g) / 2 - b):
        mu = reference_trimmed_mean(opponent)
        means.append(mu)
        variances.append(np.mean((opponent - mu) ** 2))
    return -0.0268 * math.hypot(*means) + 0.1586 * math.sqrt(sum(variances))


def reference_blocks(height: int, width: int):
    for top in range(0, height - height % 10, 10):
        for left in range(0, width - width % 10, 10):
            yield slice(top, top + 10), slice(left, left + 10)


def reference_eme(channel: np.ndarray) -> float:
    terms = []
    for rows, cols in reference_blocks(*channel.shape):
        block = channel[rows, cols]
        terms.append(math.log(block.max() / block.min()) if block.min() > 0 else 0.0)
    return 2.0 / len(terms) * sum(terms)


def reference_uism(image: np.ndarray) -> float:
    total = 0.0
    for c, weight in enumerate((0.299, 0.587, 0.114)):
        channel = 255.0 * image[..., c]
        # scipy's 'reflect' repeats the edge pixel, which is all a 3x3 stencil reads outside the image
        magnitude = np.hypot(ndimage.sobel(channel, axis=0), ndimage.sobel(channel, axis=1))
        total += weight * reference_eme(magnitude * channel)
    return total


def reference_uiconm(image: np.ndarray) -> float:
    terms = []
    for rows, cols in reference_blocks(*image.shape[:2]):
        block = 255.0 * image[rows, cols]
        high, low = block.max(), block.min()
        ratio = (high - low) / (high + low) if high + low > 0 else 0.0
        terms.append(ratio * math.log(ratio) if ratio > 0 else 0.0)
    return -sum(terms) / len(terms)


def reference_uiqm(image: np.ndarray) -> float:
    c1, c2, c3 = UIQM_WEIGHTS
    return c1 * reference_uicm(image) + c2 * reference_uism(image) + c3 * reference_uiconm(image)


# ---- test images -----------------------------------------------------------------------------------------------------


def underwater_like(height: int, width: int, seed: int) -> torch.Tensor:
    """A blue-green image with texture, a bright patch and a black corner (L = 0 and min = 0 occur)."""
    g = torch.Generator().manual_seed(seed)
    image = torch.rand(height, width, 3, generator=g, dtype=torch.float64) * torch.tensor([0.25, 0.6, 0.7])
    image += torch.tensor([0.02, 0.2, 0.25], dtype=torch.float64)
    image[: height // 3, : width // 4] = torch.tensor([0.9, 0.8, 0.6], dtype=torch.float64)
    image[-4:, -5:] = 0.0
    return image


def grey(value: float, height: int = 20, width: int = 30) -> torch.Tensor:
    return torch.full((height, width, 3), value, dtype=torch.float64)


# ---- against the papers' formulas ------------------------------------------------------------------------------------


@pytest.mark.parametrize(("height", "width", "seed"), [(23, 37, 0), (40, 30, 1), (10, 10, 2)])
def test_uciqe_and_uiqm_match_the_papers_formulas(height, width, seed):
    image = underwater_like(height, width, seed)
    array = image.numpy()
    # scikit-image's and kornia's CIELab agree to about 1e-4 in L*, a*, b*: a few 1e-6 of UCIQE
    assert float(uciqe(image)) == pytest.approx(reference_uciqe(array), abs=1e-5)
    assert float(uicm(image)) == pytest.approx(reference_uicm(array), rel=1e-10)
    assert float(uism(image)) == pytest.approx(reference_uism(array), rel=1e-10)
    assert float(uiconm(image)) == pytest.approx(reference_uiconm(array), rel=1e-10)
    assert float(uiqm(image)) == pytest.approx(reference_uiqm(array), rel=1e-10)


def test_a_batch_gives_each_image_its_own_value():
    images = torch.stack([underwater_like(24, 32, seed) for seed in range(3)])
    for metric in (uciqe, uiqm):
        batched = metric(images)
        assert batched.shape == (3,)
        assert torch.allclose(batched, torch.stack([metric(image) for image in images]), rtol=1e-12, atol=0)
    assert underwater_quality(images[0].float(), prefix="uri_") == {
        "uri_uciqe": pytest.approx(float(uciqe(images[0].float()))),
        "uri_uiqm": pytest.approx(float(uiqm(images[0].float())))}


# ---- hand computations and invariances -------------------------------------------------------------------------------


@pytest.mark.parametrize("value", [0.0, 0.2, 0.5, 1.0])
def test_a_constant_grey_image_scores_zero(value):
    # no chroma spread, no luminance contrast, no saturation; no opponent colour, no edge, no block contrast
    image = grey(value)
    assert float(uciqe(image)) == pytest.approx(0.0, abs=1e-5)  # a* and b* of grey are 0 to about 1e-5
    assert float(uicm(image)) == 0.0
    assert float(uism(image)) == 0.0
    assert float(uiconm(image)) == 0.0
    assert float(uiqm(image)) == 0.0


def test_a_grey_image_is_not_colourful():
    g = torch.Generator().manual_seed(0)
    image = torch.rand(30, 40, 1, generator=g, dtype=torch.float64).expand(-1, -1, 3)
    assert float(uicm(image)) == 0.0
    assert float(uism(image)) > 0 and float(uiconm(image)) > 0


def test_uciqe_of_half_black_half_white_is_the_luminance_weight():
    # L runs from 0 to 1 (con_l = 1); black and white have no chroma, so sigma_c = mu_s = 0
    image = grey(0.0, 10, 20)
    image[:, 10:] = 1.0
    assert float(uciqe(image)) == pytest.approx(UCIQE_WEIGHTS[1], abs=1e-5)


def test_uciqe_of_a_constant_colour_is_its_saturation():
    # sRGB red: L* = 53.2408, a* = 80.0925, b* = 67.2032 (CIE D65); one colour has no spread and no contrast
    image = torch.zeros(12, 12, 3, dtype=torch.float64)
    image[..., 0] = 1.0
    saturation = math.hypot(80.0925, 67.2032) / 255 / (53.2408 / 100)
    assert float(uciqe(image)) == pytest.approx(UCIQE_WEIGHTS[2] * saturation, rel=1e-4)


def test_uicm_of_a_constant_colour_is_its_opponent_length():
    image = torch.zeros(10, 10, 3, dtype=torch.float64)
    image[...] = torch.tensor([0.8, 0.4, 0.2], dtype=torch.float64)
    rg, yb = 255 * (0.8 - 0.4), 255 * ((0.8 + 0.4) / 2 - 0.2)
    assert float(uicm(image)) == pytest.approx(-0.0268 * math.hypot(rg, yb), rel=1e-12)


def test_uicm_trims_a_tenth_at_each_end():
    # RG over 20 pixels: 0..17 and two outliers; the trimmed mean drops 2 at each end (-300, 0 and 17, 200): the
    # mean of 1..16 is 8.5; the spread is around it over all 20
    rg = torch.tensor([*range(18), 200.0, -300.0], dtype=torch.float64) / 255
    image = torch.zeros(4, 5, 3, dtype=torch.float64)
    image[..., 0] = 0.5 + rg.reshape(4, 5) / 2
    image[..., 1] = 0.5 - rg.reshape(4, 5) / 2
    image[..., 2] = 0.5  # YB = (R + G) / 2 - B = 0 everywhere
    values = 255 * rg.numpy()
    sigma = math.sqrt(np.mean((values - 8.5) ** 2))
    assert float(uicm(image)) == pytest.approx(-0.0268 * 8.5 + 0.1586 * sigma, rel=1e-10)


def test_uism_of_a_ramp():
    # I = c (x + 1) in one 10x10 block: Sobel's x-derivative is 8c inside and 4c at the repeated edges, none in y;
    # |edge| x I is smallest at x = 0 (4c * c) and largest at x = 8 (8c * 9c): EME = 2 ln 18, in every channel
    c = 0.05
    ramp = (c * (torch.arange(10, dtype=torch.float64) + 1))[None, :, None].expand(10, 10, 3)
    assert float(uism(ramp)) == pytest.approx(2 * math.log(18), rel=1e-12)


def test_uiconm_of_two_greys():
    # every block holds 0.2 and 0.6: r = 0.4 / 0.8 = 1/2, UIConM = -(1/2) ln(1/2) = ln(2) / 2
    image = grey(0.2, 20, 30)
    image[::2] = 0.6
    assert float(uiconm(image)) == pytest.approx(math.log(2) / 2, rel=1e-12)


def test_uism_and_uiconm_do_not_depend_on_the_scale_and_uicm_is_linear_in_it():
    image = underwater_like(30, 40, 3)
    assert float(uism(0.5 * image)) == pytest.approx(float(uism(image)), rel=1e-12)
    assert float(uiconm(0.5 * image)) == pytest.approx(float(uiconm(image)), rel=1e-12)
    assert float(uicm(0.5 * image)) == pytest.approx(0.5 * float(uicm(image)), rel=1e-12)


def test_rows_and_columns_beyond_the_last_full_block_do_not_count():
    image = underwater_like(20, 30, 4)
    padded = torch.cat([image, torch.rand(20, 9, 3, dtype=torch.float64)], dim=1)
    assert float(uism(padded[:, :30])) == float(uism(image))
    assert float(uiconm(padded)) == pytest.approx(float(uiconm(image)), rel=1e-12)


def test_an_image_smaller_than_a_block_has_no_uiqm():
    with pytest.raises(ValueError, match="at least 10x10"):
        uiqm(grey(0.3, 9, 30))
    assert underwater_quality(grey(0.3, 9, 30).float())["uiqm"] is None
    with pytest.raises(ValueError, match=r"\[H, W, 3\]"):
        uciqe(torch.zeros(10, 10))
