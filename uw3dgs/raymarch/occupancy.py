"""An occupancy (alpha-mask) grid that lets ray marching skip empty space (TensoRF's `AlphaGridMask`).

Built from a density: alpha = 1 - exp(-sigma * step) at the vertices of a regular grid over a box, dilated by a max
filter (`dilation` voxels wide), and thresholded. A point is occupied where the trilinear interpolation of that
binary grid is positive, i.e. where any of the 8 grid vertices around it is occupied. For a density that is
trilinear within each cell of the same grid and monotone in it (a VM field read at its own resolution, through ReLU
or softplus), this never skips a point whose alpha is at least the threshold: such a point has a cell vertex at least
as dense. An empty grid (no build yet) marks everything occupied.
"""

from __future__ import annotations

from collections.abc import Callable

import torch
import torch.nn.functional as F
from torch import Tensor, nn


def grid_vertices(lo: Tensor, hi: Tensor, resolution: tuple[int, int, int]) -> Tensor:
    """The vertices [X, Y, Z, 3] of a regular grid with `resolution` (X, Y, Z) vertices spanning [lo, hi]."""
    axes = [torch.linspace(float(lo[i]), float(hi[i]), int(resolution[i]), device=lo.device) for i in range(3)]
    return torch.stack(torch.meshgrid(*axes, indexing="ij"), dim=-1)


class OccupancyGrid(nn.Module):
    """Buffers: `lo`, `hi` [3] the box (in the space the sampler puts its points in), `volume` [Z, Y, X] 1 where
    occupied (empty until `build`)."""

    def __init__(self, lo: Tensor, hi: Tensor):
        super().__init__()
        self.register_buffer("lo", lo.detach().clone().float())
        self.register_buffer("hi", hi.detach().clone().float())
        self.register_buffer("volume", torch.zeros(0, 0, 0))

    @property
    def built(self) -> bool:
        return self.volume.numel() > 0

    @torch.no_grad()
    def build(self, density: Callable[[Tensor], Tensor], lo: Tensor, hi: Tensor, resolution: tuple[int, int, int],
              step: float, threshold: float, dilation: int = 3, chunk: int = 1 << 18) -> None:
        """Evaluate `density(points [N, 3]) -> [N]` at the grid's vertices over [lo, hi] and keep the vertices whose
        dilated alpha = 1 - exp(-density * step) is at least `threshold`."""
        vertices = grid_vertices(lo, hi, resolution).reshape(-1, 3)
        sigma = torch.cat([density(part) for part in vertices.split(chunk)])
        alpha = -torch.expm1(-sigma * step).reshape(*resolution)
        alpha = alpha.permute(2, 1, 0).contiguous()[None, None]  # [1, 1, Z, Y, X], grid_sample's order
        if dilation > 1:
            alpha = F.max_pool3d(alpha, kernel_size=dilation, stride=1, padding=dilation // 2)
        self.lo.copy_(lo)
        self.hi.copy_(hi)
        self.volume = (alpha[0, 0] >= threshold).float()

    def occupied(self, points: Tensor) -> Tensor:
        """Whether each of `points` [N, 3] may hold density [N] (True everywhere before `build`)."""
        if not self.built:
            return torch.ones(points.shape[:-1], dtype=torch.bool, device=points.device)
        u = (points - self.lo) / (self.hi - self.lo) * 2 - 1
        value = F.grid_sample(self.volume[None, None].to(points.dtype), u.reshape(1, -1, 1, 1, 3),
                              align_corners=True).reshape(points.shape[:-1])
        return value > 0

    def occupied_bounds(self) -> tuple[Tensor, Tensor] | None:
        """(lo [3], hi [3]) of the occupied vertices, None if none is."""
        if not self.built or not bool(self.volume.any()):
            return None
        occupied = self.volume.permute(2, 1, 0) > 0  # [X, Y, Z]
        first, last = [], []
        for axis in range(3):
            others = tuple(a for a in range(3) if a != axis)
            hit = torch.nonzero(occupied.any(dim=others)).flatten()
            size = max(occupied.shape[axis] - 1, 1)
            first.append(float(hit[0]) / size)
            last.append(float(hit[-1]) / size)
        span = self.hi - self.lo
        first_t, last_t = (torch.tensor(v, device=span.device) for v in (first, last))
        return self.lo + first_t * span, self.lo + last_t * span
