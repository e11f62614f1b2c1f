"""Where a ray is sampled: uniformly in a box of the world (TensoRF's `sample_ray`), or uniformly in normalised
device coordinates of a reference camera for forward-facing scenes (TensoRF's `sample_ray_ndc`, NeRF's LLFF NDC).

Both return `RaySamples`: the points in the sampler's space (where the field lives), the intervals the density is
integrated over in that space, and each sample's distance along the ray in the world (what depth and the medium
use). Jitter comes from torch's global generator (checkpointed with the run)."""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import Tensor

from uw3dgs.cameras import Camera
from uw3dgs.raymarch.rays import RayBundle


@dataclass
class RaySamples:
    """S samples on each of R rays.

    points [R, S, 3]: in the sampler's space (the world for `BoxSampler`, NDC for `NDCSampler`);
    deltas [R, S]: length of the interval after each sample in that space (the last is 0, as in TensoRF);
    ranges [R, S]: distance of each sample from the ray's origin in world units (inf at or past infinity);
    valid [R, S]: the sample lies inside the sampler's box;
    viewdirs [R, 3]: unit ray directions in the sampler's space (what a view-dependent field sees)."""

    points: Tensor
    deltas: Tensor
    ranges: Tensor
    valid: Tensor
    viewdirs: Tensor


def inside(points: Tensor, lo: Tensor, hi: Tensor) -> Tensor:
    return ((points >= lo) & (points <= hi)).all(dim=-1)


def interval_lengths(t: Tensor) -> Tensor:
    """t [R, S] -> the length after each sample [R, S], 0 after the last (TensoRF's `dists`)."""
    return torch.cat([t[:, 1:] - t[:, :-1], torch.zeros_like(t[:, :1])], dim=-1)


class BoxSampler:
    """Samples every `step` world units from where the ray enters the box [lo, hi] (not before `near`, not after
    `far`), one random offset per ray while training (TensoRF's `sample_ray`)."""

    def __init__(self, lo: Tensor, hi: Tensor, near: float, far: float):
        self.lo, self.hi, self.near, self.far = lo, hi, float(near), float(far)

    def __call__(self, rays: RayBundle, num_samples: int, step: float, jitter: bool) -> RaySamples:
        o, d = rays.origins, rays.directions
        lo, hi = self.lo.to(o), self.hi.to(o)
        safe = torch.where(d == 0, torch.full_like(d, 1e-6), d)
        t_enter = torch.minimum((hi - o) / safe, (lo - o) / safe).amax(-1).clamp(self.near, self.far)
        ticks = torch.arange(num_samples, device=o.device, dtype=o.dtype)[None].expand(len(o), -1)
        if jitter:
            ticks = ticks + torch.rand(len(o), 1, device=o.device, dtype=o.dtype)
        t = t_enter[:, None] + step * ticks
        points = o[:, None] + d[:, None] * t[..., None]
        return RaySamples(points, interval_lengths(t), t, inside(points, lo, hi), d)


def average_camera(cameras: list[Camera]) -> tuple[Tensor, Tensor]:
    """The mean pose of `cameras` (LLFF's `average_poses` in OpenCV axes): (R [3, 3] world-to-camera rotation whose
    z row is the mean viewing direction, centre [3] the mean camera centre)."""
    rotations = torch.stack([c.viewmat[:3, :3] for c in cameras]).double()
    z = torch.nn.functional.normalize(rotations[:, 2].mean(0), dim=0)
    y_mean = rotations[:, 1].mean(0)
    x = torch.nn.functional.normalize(torch.linalg.cross(y_mean, z), dim=0)
    y = torch.linalg.cross(z, x)
    center = torch.stack([c.center for c in cameras]).double().mean(0)
    return torch.stack([x, y, z]).float(), center.float()


class NDCSampler:
    """Samples uniformly in t in [0, 1] along each ray's NDC image (t = 0 at the near plane `near_plane` in front of
    the reference camera, t = 1 at infinity; TensoRF's `sample_ray_ndc` on LLFF's `ndc_rays_blender`), the same
    random offsets for every ray while training, as TensoRF draws them.

    NDC of the reference camera (rotation `R` world-to-camera, `center`, focal lengths `fx`, `fy` in pixels of a
    `width` x `height` image), in OpenCV axes: a camera-frame point (x, y, z) maps to
    (fx / (W / 2) x / z, fy / (H / 2) y / z, 1 - 2 near / z), so z_ndc = -1 at the near plane and 1 at infinity.
    A sample at t has depth near / (1 - t) in the reference frame, which gives its world distance along the ray."""

    def __init__(self, R: Tensor, center: Tensor, fx: float, fy: float, width: int, height: int,
                 near_plane: float, lo: Tensor, hi: Tensor):
        self.R, self.center = R, center
        self.ax, self.ay = 2.0 * float(fx) / width, 2.0 * float(fy) / height
        self.near_plane = float(near_plane)
        self.lo, self.hi = lo, hi

    def to_reference(self, rays: RayBundle) -> tuple[Tensor, Tensor]:
        R, c = self.R.to(rays.origins), self.center.to(rays.origins)
        return (rays.origins - c) @ R.T, rays.directions @ R.T

    def __call__(self, rays: RayBundle, num_samples: int, jitter: bool) -> RaySamples:
        o_c, d_c = self.to_reference(rays)
        n = self.near_plane
        forward = d_c[:, 2] > 1e-6
        dz = torch.where(forward, d_c[:, 2], torch.ones_like(d_c[:, 2]))
        shift = (n - o_c[:, 2]) / dz
        o_n = o_c + shift[:, None] * d_c  # on the near plane: z = near
        ox, oy = o_n[:, 0] / n, o_n[:, 1] / n
        origin = torch.stack([self.ax * ox, self.ay * oy, torch.full_like(ox, -1.0)], dim=-1)
        direction = torch.stack([self.ax * (d_c[:, 0] / dz - ox), self.ay * (d_c[:, 1] / dz - oy),
                                 torch.full_like(ox, 2.0)], dim=-1)
        t = torch.linspace(0.0, 1.0, num_samples, device=o_c.device, dtype=o_c.dtype)[None]
        if jitter:
            t = t + torch.rand_like(t) / num_samples
        t = t.expand(len(o_c), -1)
        points = origin[:, None] + direction[:, None] * t[..., None]
        norm = direction.norm(dim=-1, keepdim=True)
        deltas = interval_lengths(t) * norm
        finite = t < 1.0
        depth = n / torch.where(finite, 1.0 - t, torch.ones_like(t))
        ranges = torch.where(finite & forward[:, None], (depth - o_c[:, 2:3]) / dz[:, None],
                             torch.full_like(t, float("inf")))
        valid = inside(points, self.lo.to(points), self.hi.to(points)) & forward[:, None]
        return RaySamples(points, deltas, ranges, valid, direction / norm)
