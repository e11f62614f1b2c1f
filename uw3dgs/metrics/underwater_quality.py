"""No-reference underwater image quality: UCIQE (Yang & Sowmya 2015) and UIQM (Panetta, Gao & Agaian 2016).

Both score one image alone (no clean truth needed), so they measure the water-free image (URI) of a real dive where
PSNR cannot. Images are [H, W, 3] or [B, H, W, 3] RGB in [0, 1] (sRGB-encoded, as rendered and stored); every
function returns one value per image (a 0-dim tensor for [H, W, 3], [B] for a batch), computed in float64 without
gradients. Both reward saturated, contrasty colour whether or not it is true: a check of a restoration, never a
training goal (docs/underwater-quality.md).

UCIQE = 0.4680 sigma_c + 0.2745 con_l + 0.2576 mu_s, in CIELab (D65, 2 degree observer; `kornia.color.rgb_to_lab`)
scaled as the widely used Python implementations scale OpenCV's 8-bit Lab (each channel / 255): L = L*/100 in
[0, 1], a = a*/255, b = b*/255, but with a and b centred (8-bit Lab stores a* + 128, b* + 128; those offsets are
left out, so a neutral grey has chroma 0 as CIELab says):
- sigma_c: the standard deviation (over pixels, 1/N) of the chroma C = sqrt(a^2 + b^2);
- con_l: the contrast of luminance, L at rank floor(0.99 N) minus L at rank floor(0.01 N) of the N sorted pixels;
- mu_s: the mean saturation C / L (0 where L = 0).

UIQM = 0.0282 UICM + 0.2953 UISM + 3.5753 UIConM, on R, G, B scaled to [0, 255], in the form of the widely copied
Python implementation (FUnIE-GAN's `uqim_utils.py`) but with the paper's blue weight 0.114 (docs/underwater-quality.md
lists the differences):
- UICM (colourfulness) = -0.0268 sqrt(mu_RG^2 + mu_YB^2) + 0.1586 sqrt(s_RG^2 + s_YB^2) of the opponent colours
  RG = R - G and YB = (R + G) / 2 - B over all pixels; mu is the alpha-trimmed mean (sorted values, the
  ceil(0.1 K) smallest and floor(0.1 K) largest of the K dropped) and s^2 = (1/K) sum (x - mu)^2 over all K.
- UISM (sharpness) = 0.299 EME(R) + 0.587 EME(G) + 0.114 EME(B) of each channel's Sobel magnitude times the
  channel itself (3x3 Sobel with the edge pixel repeated at the border; components below SOBEL_ROUNDING are 0);
  EME(x) = 2 / (k1 k2) sum over the k1 x k2 blocks of 10 x 10 pixels of ln(max / min) (0 for a block whose min
  is 0).
- UIConM (contrast) = -1 / (k1 k2) sum over the same blocks of r ln r, r = (max - min) / (max + min) over the
  block's pixels of all three channels (0 where max - min or max + min is 0): logAMEE in ordinary arithmetic.
The blocks tile the image from its top-left corner; the last H % 10 rows and W % 10 columns are not used, so an
image needs at least 10 x 10 pixels.
"""

from __future__ import annotations

import math

import kornia
import torch
from torch import Tensor

UCIQE_WEIGHTS = (0.4680, 0.2745, 0.2576)
"""(c1, c2, c3) of sigma_c, con_l and mu_s: Yang & Sowmya's fitted weights."""
LUMINANCE_TAIL = 0.01
"""con_l is the luminance at the (1 - tail) rank minus that at the tail rank."""
LAB_SCALE = (100.0, 255.0, 255.0)
"""L*, a*, b* are divided by these: the common implementations' 8-bit Lab / 255, without the a/b offsets."""

UIQM_WEIGHTS = (0.0282, 0.2953, 3.5753)
"""(c1, c2, c3) of UICM, UISM and UIConM: Panetta et al.'s weights."""
UICM_WEIGHTS = (-0.0268, 0.1586)
"""UICM's weights of the opponent colours' mean length and of their spread."""
UICM_TRIM = 0.1
"""alpha_L = alpha_R: the share of the sorted opponent values dropped at each end for the trimmed mean."""
UISM_CHANNEL_WEIGHTS = (0.299, 0.587, 0.114)
"""lambda_R, lambda_G, lambda_B: the luma weights of the three channels' EME (the paper's)."""
BLOCK = 10
"""Side in pixels of the square blocks of EME and logAMEE."""
SOBEL_ROUNDING = 1e-12
"""Sobel components of at most this size (images in [0, 1], float64) are float rounding of a flat region and count as
0, as exact arithmetic gives (kornia's 3x3 convolution leaves about 1e-16 there, which EME's ln(max / min) would
turn into a large term; a real difference of two float32 pixel values is far above it)."""
PIXEL_SCALE = 255.0
"""UIQM reads R, G, B in [0, 255]; only UICM depends on the scale (UISM and UIConM are ratios)."""


def _batched(image: Tensor) -> tuple[Tensor, bool]:
    """[B, H, W, 3] float64 without gradient from [H, W, 3] or [B, H, W, 3]; and whether it came batched."""
    if image.ndim not in (3, 4) or image.shape[-1] != 3:
        raise ValueError(f"expected [H, W, 3] or [B, H, W, 3] RGB images, got shape {tuple(image.shape)}")
    batched = image.ndim == 4
    return (image if batched else image[None]).detach().to(torch.float64), batched


def _unbatched(values: Tensor, batched: bool) -> Tensor:
    return values if batched else values[0]


def _blocks(images: Tensor) -> Tensor:
    """[B, k2, k1, BLOCK * BLOCK * C] from [B, H, W, C]: the BLOCK x BLOCK tiles from the top-left corner, the
    last H % BLOCK rows and W % BLOCK columns dropped. ValueError for an image smaller than one block."""
    b, h, w, c = images.shape
    k2, k1 = h // BLOCK, w // BLOCK
    if k1 == 0 or k2 == 0:
        raise ValueError(f"UIQM needs images of at least {BLOCK}x{BLOCK} pixels (its {BLOCK}x{BLOCK} blocks), got "
                         f"{w}x{h}")
    tiles = images[:, :k2 * BLOCK, :k1 * BLOCK].reshape(b, k2, BLOCK, k1, BLOCK, c)
    return tiles.permute(0, 1, 3, 2, 4, 5).reshape(b, k2, k1, BLOCK * BLOCK * c)


def cielab(image: Tensor) -> Tensor:
    """CIELab (D65, 2 degree observer) of sRGB `image` [..., H, W, 3] in [0, 1]: [..., H, W, 3] with L* in
    [0, 100] and a*, b* about [-128, 127], through kornia (which decodes the sRGB gamma first)."""
    return kornia.color.rgb_to_lab(image.movedim(-1, -3)).movedim(-3, -1)


def uciqe(image: Tensor) -> Tensor:
    """UCIQE of RGB `image` [H, W, 3] or [B, H, W, 3] in [0, 1], one value per image (module docstring)."""
    images, batched = _batched(image)
    lab = cielab(images).flatten(1, 2) / images.new_tensor(LAB_SCALE)  # [B, N, 3]
    lum, chroma = lab[..., 0], lab[..., 1:].norm(dim=-1)
    sigma_c = chroma.std(dim=1, correction=0)
    ranked = lum.sort(dim=1).values
    n = ranked.shape[1]
    con_l = ranked[:, int((1.0 - LUMINANCE_TAIL) * n)] - ranked[:, int(LUMINANCE_TAIL * n)]
    saturation = torch.where(lum > 0, chroma / lum.clamp_min(torch.finfo(lum.dtype).tiny), 0.0)
    mu_s = saturation.mean(dim=1)
    c1, c2, c3 = UCIQE_WEIGHTS
    return _unbatched(c1 * sigma_c + c2 * con_l + c3 * mu_s, batched)


def _trimmed_mean(values: Tensor, trim: float) -> Tensor:
    """Mean [B] of values [B, K] without the ceil(trim K) smallest and floor(trim K) largest of each row."""
    k = values.shape[1]
    low, high = math.ceil(round(trim * k, 9)), math.floor(round(trim * k, 9))  # round: 0.1 * 30 is not 3.0
    return values.sort(dim=1).values[:, low:k - high].mean(dim=1)


def uicm(image: Tensor) -> Tensor:
    """UIQM's colourfulness UICM of RGB `image` [H, W, 3] or [B, H, W, 3] in [0, 1], one value per image; 0 for a
    grey image (module docstring)."""
    images, batched = _batched(image)
    r, g, b = (PIXEL_SCALE * images.flatten(1, 2)).unbind(-1)
    length, spread = [], []
    for opponent in (r - g, 0.5 * (r + g) - b):
        mu = _trimmed_mean(opponent, UICM_TRIM)
        length.append(mu.square())
        spread.append((opponent - mu[:, None]).square().mean(dim=1))
    w_length, w_spread = UICM_WEIGHTS
    return _unbatched(w_length * sum(length).sqrt() + w_spread * sum(spread).sqrt(), batched)


def _eme(maps: Tensor) -> Tensor:
    """EME [B, C] of per-channel maps [B, H, W, C]: 2 / (k1 k2) sum over blocks of ln(max / min), 0 where min = 0."""
    b, h, w, c = maps.shape
    tiles = _blocks(maps).reshape(b, h // BLOCK, w // BLOCK, BLOCK * BLOCK, c)
    high, low = tiles.amax(dim=3), tiles.amin(dim=3)
    terms = torch.where(low > 0, torch.log(high / low.clamp_min(torch.finfo(low.dtype).tiny)), 0.0)
    return 2.0 * terms.mean(dim=(1, 2))


def uism(image: Tensor) -> Tensor:
    """UIQM's sharpness UISM of RGB `image` [H, W, 3] or [B, H, W, 3] in [0, 1], one value per image (module
    docstring); independent of the image's scale."""
    images, batched = _batched(image)
    channels = images.permute(0, 3, 1, 2)  # [B, 3, H, W]
    gradient = kornia.filters.spatial_gradient(channels, mode="sobel", normalized=False)  # [B, 3, 2, H, W]
    gradient = torch.where(gradient.abs() > SOBEL_ROUNDING, gradient, 0.0)
    edges = torch.hypot(gradient[:, :, 0], gradient[:, :, 1]) * channels
    eme = _eme(edges.permute(0, 2, 3, 1))
    return _unbatched(eme @ images.new_tensor(UISM_CHANNEL_WEIGHTS), batched)


def uiconm(image: Tensor) -> Tensor:
    """UIQM's contrast UIConM of RGB `image` [H, W, 3] or [B, H, W, 3] in [0, 1], one value per image (module
    docstring); independent of the image's scale."""
    images, batched = _batched(image)
    tiles = _blocks(images)
    high, low = tiles.amax(dim=-1), tiles.amin(dim=-1)
    spread, total = high - low, high + low
    ratio = spread / total.clamp_min(torch.finfo(total.dtype).tiny)
    terms = torch.where((spread > 0) & (total > 0), ratio * torch.log(ratio.clamp_min(torch.finfo(ratio.dtype).tiny)),
                        0.0)
    return _unbatched(0.0 - terms.mean(dim=(1, 2)), batched)  # 0.0 - : no -0.0 in the JSON


def uiqm(image: Tensor) -> Tensor:
    """UIQM of RGB `image` [H, W, 3] or [B, H, W, 3] in [0, 1], one value per image (module docstring);
    ValueError for an image smaller than one 10 x 10 block."""
    c1, c2, c3 = UIQM_WEIGHTS
    return c1 * uicm(image) + c2 * uism(image) + c3 * uiconm(image)


def underwater_quality(image: Tensor, prefix: str = "") -> dict[str, float | None]:
    """{prefix}uciqe and {prefix}uiqm of one RGB image [H, W, 3] in [0, 1], for uw-eval's rows; uiqm is None (a
    missing value) for an image smaller than one UIQM block."""
    too_small = min(image.shape[0], image.shape[1]) < BLOCK
    return {f"{prefix}uciqe": float(uciqe(image)), f"{prefix}uiqm": None if too_small else float(uiqm(image))}
