"""The water as a function of the viewing direction alone (WaterSplatting's medium MLP): a spherical-harmonics
encoding of each pixel's world-space ray direction, a small MLP, and per channel c_med (sigmoid), sigma_bs and
sigma_attn (softplus). Evaluated once per pixel; no position, so the water is the same along a ray and between
rays of one direction."""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import Tensor, nn

from uw3dgs.cameras import Camera
from uw3dgs.options import CheckedConfig, check_number
from uw3dgs.render.medium_types import PixelMedium
from uw3dgs.render.sh import MAX_DEGREE, num_sh_bases, sh_basis


@dataclass(frozen=True)
class DirectionMediumConfig(CheckedConfig):
    sh_degree: int = 3
    """Degree of the direction's SH encoding: 3 = 4 levels, 16 values (WaterSplatting's SHEncoding(levels=4))."""
    num_layers: int = 2
    """Linear layers of the MLP, counted as nerfstudio's MLP does: 2 = one hidden layer, then the 9 outputs."""
    hidden_dim: int = 128
    """Width of the hidden layers."""
    density_bias: float = 0.0
    """Added to the sigma outputs before the softplus (WaterSplatting's medium_density_bias)."""

    def check_options(self) -> None:
        check_number(self, "sh_degree", ge=0, le=MAX_DEGREE, integer=True)
        check_number(self, "num_layers", ge=1, integer=True)
        check_number(self, "hidden_dim", ge=1, integer=True)


class DirectionMedium(nn.Module):
    """c_med, sigma_bs, sigma_attn [..., 3] each from unit world-space directions [..., 3]; sigmas per unit of
    camera-space depth in the scene's (normalised) units. Hidden layers use sigmoid activations, as theirs."""

    def __init__(self, config: DirectionMediumConfig):
        super().__init__()
        self.config = config
        width, layers = config.hidden_dim, []
        in_dim = num_sh_bases(config.sh_degree)
        for _ in range(config.num_layers - 1):
            layers += [nn.Linear(in_dim, width), nn.Sigmoid()]
            in_dim = width
        self.mlp = nn.Sequential(*layers, nn.Linear(in_dim, 9))

    def forward(self, dirs: Tensor) -> tuple[Tensor, Tensor, Tensor]:
        raw = self.mlp(sh_basis(self.config.sh_degree, dirs))
        sigmas = nn.functional.softplus(raw[..., 3:] + self.config.density_bias)
        return torch.sigmoid(raw[..., :3]), sigmas[..., :3], sigmas[..., 3:]

    def pixel_medium(self, camera: Camera) -> PixelMedium:
        """The water of every pixel of `camera`, [H, W, 3] each, from its ray direction through the pixel centre."""
        dirs = camera.ray_directions().to(self.mlp[-1].weight.dtype)
        return PixelMedium(*self(dirs))
