"""Inputs and outputs of the medium compositor (WaterSplatting's compositing: the water integrated between
depth-sorted Gaussians), shared by its backends."""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import Tensor

from uw3dgs.render.types import RasterOutput


@dataclass
class PixelMedium:
    """The water seen along each pixel's ray, [H, W, 3] each (RGB): `color` c_med in [0, 1], the light the water
    scatters towards the camera; `sigma_bs` (backscatter) and `sigma_attn` (attenuation), >= 0, per unit of
    camera-space depth."""

    color: Tensor
    sigma_bs: Tensor
    sigma_attn: Tensor
    packed_values: Tensor | None = None
    """The three as one [H, W, 9] tensor, when whoever made them has it (their views into it): `packed` returns it
    instead of a copy, and gradients reach it without being split and gathered again."""

    def check(self, width: int, height: int) -> None:
        """ValueError unless all three are [height, width, 3]."""
        for name in ("color", "sigma_bs", "sigma_attn"):
            shape = tuple(getattr(self, name).shape)
            if shape != (height, width, 3):
                raise ValueError(f"PixelMedium.{name} must be [{height}, {width}, 3] for this view, got {list(shape)}")

    def packed(self) -> Tensor:
        """[H, W, 9]: color, sigma_bs, sigma_attn along the last dim."""
        if self.packed_values is not None:
            return self.packed_values
        return torch.cat([self.color, self.sigma_bs, self.sigma_attn], dim=-1)


@dataclass
class MediumRasterOutput(RasterOutput):
    """A `RasterOutput` whose `render` is the restored image (sum_i w_i c_i: no water), with the water's two parts.

    With w_i = alpha_i T_i the blending weights of the depth-sorted Gaussians (3DGS's transmittance T_i, no medium in
    it), z_i the camera-space depth of Gaussian i's centre and z_0 = 0, per pixel and channel:
    `object` [H, W, 3] = sum_i w_i c_i exp(-sigma_attn z_i), the Gaussians' light attenuated on its way to the camera;
    `medium` [H, W, 3] = sum_i T_i (exp(-sigma_bs z_{i-1}) - exp(-sigma_bs z_i)) c_med + T_final exp(-sigma_bs z_N)
    c_med, the water between consecutive blended Gaussians and behind the last one, out to infinity (which telescopes
    to c_med (1 - sum_i w_i exp(-sigma_bs z_i))). The underwater image is object + medium. Depths take no gradient
    (as in WaterSplatting's kernel): `depths` and `depth` carry none to the projection. `absgrad` [N, 2]: after a
    backward, each Gaussian's per-pixel screen-space gradients summed in absolute value (x, y; pixels), for
    absolute-gradient densification; zeros before (and None when not asked for)."""

    object: Tensor | None = None
    medium: Tensor | None = None
    absgrad: Tensor | None = None

    @property
    def underwater(self) -> Tensor:
        """[H, W, 3] object + medium: what the camera sees."""
        return self.object + self.medium
