"""The water as a function of the viewing direction alone (WaterSplatting's medium MLP): a spherical-harmonics
encoding of each pixel's world-space ray direction, a small MLP, and per channel c_med (sigmoid), sigma_bs and
sigma_attn (softplus). Evaluated once per pixel; no position, so the water is the same along a ray and between
rays of one direction."""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import Tensor, nn
from torch.autograd.function import once_differentiable

from uw3dgs.cameras import Camera
from uw3dgs.kernels.direction_mlp import direction_mlp
from uw3dgs.kernels.policy import Kernels, use_compiled
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


ROWS_PER_BLOCK = 2048
"""Rows (pixels) `_SigmoidMLP` works on at a time: a block's hidden activations ([width, rows]) stay in a core's cache
between the products of the forward and of the backward."""


class _SigmoidMLP(torch.autograd.Function):
    """`DirectionMedium.mlp` (Linear, Sigmoid, ..., Linear) on rows x [P, in] -> [P, out], given its weights and
    biases in order: the same function as the module, with a hand-written backward, faster on the CPU for one row per
    pixel. It runs feature-major ([features, rows], so every product is one well-shaped matrix product) on blocks of
    ROWS_PER_BLOCK rows, keeps only the hidden activations for the backward, and sums the weights' gradients over
    the blocks in order (deterministic)."""

    @staticmethod
    def forward(ctx, x: Tensor, *params: Tensor) -> Tensor:
        out, hidden = [], []
        for block in x.split(ROWS_PER_BLOCK):
            h = block.t()
            for i in range(0, len(params), 2):
                h = torch.addmm(params[i + 1][:, None], params[i], h)
                if i + 2 < len(params):
                    h = h.sigmoid_()
                    hidden.append(h)
            out.append(h)
        ctx.save_for_backward(x, *params, *hidden)
        ctx.num_params = len(params)
        return torch.cat(out, dim=1).t()

    @staticmethod
    @once_differentiable
    def backward(ctx, grad: Tensor) -> tuple[Tensor | None, ...]:
        x, *rest = ctx.saved_tensors
        params, hidden = rest[: ctx.num_params], rest[ctx.num_params :]
        num_layers = len(params) // 2
        grads: list[Tensor | None] = [None, *(torch.zeros_like(p) for p in params)]
        grad_x = []
        for b, (block, grad_block) in enumerate(zip(x.split(ROWS_PER_BLOCK), grad.split(ROWS_PER_BLOCK),
                                                    strict=True)):
            acts = hidden[b * (num_layers - 1) : (b + 1) * (num_layers - 1)]
            g = grad_block.t()  # dL/d(pre-activation) of the current layer, [features, rows]
            for layer in reversed(range(num_layers)):
                weight = params[2 * layer]
                grads[1 + 2 * layer].addmm_(g, acts[layer - 1].t() if layer else block)
                grads[2 + 2 * layer] += g.sum(1)
                if layer:
                    g = torch.ops.aten.sigmoid_backward(weight.t() @ g, acts[layer - 1])
                elif ctx.needs_input_grad[0]:
                    grad_x.append((weight.t() @ g).t())
        if grad_x:
            grads[0] = torch.cat(grad_x)
        return tuple(grads)


class _WaterHeads(torch.autograd.Function):
    """The MLP's raw outputs [P, 9] -> [P, 9]: c_med = sigmoid(raw[:, :3]), then sigma_bs, sigma_attn =
    softplus(raw[:, 3:] + density_bias), into one contiguous tensor (the compositor reads the three packed), with
    PyTorch's own sigmoid and softplus and their backward."""

    @staticmethod
    def forward(ctx, raw: Tensor, density_bias: float) -> Tensor:
        out = raw.new_empty(raw.shape)
        torch.sigmoid(raw[:, :3], out=out[:, :3])
        shifted = raw[:, 3:] + density_bias
        out[:, 3:] = nn.functional.softplus(shifted)
        ctx.save_for_backward(out, shifted)
        return out

    @staticmethod
    @once_differentiable
    def backward(ctx, grad: Tensor) -> tuple[Tensor, None]:
        out, shifted = ctx.saved_tensors
        grad_raw = grad.new_empty(grad.shape)
        grad_raw[:, :3] = torch.ops.aten.sigmoid_backward(grad[:, :3], out[:, :3])
        grad_raw[:, 3:] = torch.ops.aten.softplus_backward(grad[:, 3:], shifted, 1.0, 20.0)
        return grad_raw, None


class DirectionMedium(nn.Module):
    """c_med, sigma_bs, sigma_attn [..., 3] each from unit world-space directions [..., 3]; sigmas per unit of
    camera-space depth in the scene's (normalised) units. Hidden layers use sigmoid activations, as theirs.
    `kernels` (the model's `--model.kernels`): 'compiled' runs the MLP with its activations as one compiled kernel
    (`uw3dgs/kernels/direction_mlp.py`) where it runs (CPU tensors, one hidden layer, directions needing no
    gradient), PyTorch elsewhere; 'torch' always PyTorch (the reference)."""

    def __init__(self, config: DirectionMediumConfig, kernels: Kernels = "compiled"):
        super().__init__()
        self.config = config
        self.kernels = kernels
        width, layers = config.hidden_dim, []
        in_dim = num_sh_bases(config.sh_degree)
        for _ in range(config.num_layers - 1):
            layers += [nn.Linear(in_dim, width), nn.Sigmoid()]
            in_dim = width
        self.mlp = nn.Sequential(*layers, nn.Linear(in_dim, 9))

    def packed(self, dirs: Tensor) -> Tensor:
        """[..., 9]: c_med, sigma_bs, sigma_attn (3 each) for unit directions [..., 3]."""
        basis = sh_basis(self.config.sh_degree, dirs)
        params = [p for layer in self.mlp if isinstance(layer, nn.Linear) for p in (layer.weight, layer.bias)]
        rows = basis.reshape(-1, basis.shape[-1])
        if len(params) == 4 and not rows.requires_grad and use_compiled(self.kernels, rows):
            return direction_mlp(rows, *params, self.config.density_bias).view(*basis.shape[:-1], 9)
        raw = _SigmoidMLP.apply(rows, *params)
        return _WaterHeads.apply(raw, self.config.density_bias).view(*basis.shape[:-1], 9)

    def forward(self, dirs: Tensor) -> tuple[Tensor, Tensor, Tensor]:
        values = self.packed(dirs)
        return values[..., :3], values[..., 3:6], values[..., 6:]

    def pixel_medium(self, camera: Camera) -> PixelMedium:
        """The water of every pixel of `camera`, [H, W, 3] each, from its ray direction through the pixel centre."""
        values = self.packed(camera.ray_directions().to(self.mlp[-1].weight.dtype))
        return PixelMedium(values[..., :3], values[..., 3:6], values[..., 6:], packed_values=values)
