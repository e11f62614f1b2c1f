"""The co-visibility mask (test pixels whose surface some training view has in its field of view)."""

from __future__ import annotations

import math

import torch

from uw3dgs.cameras import Camera
from uw3dgs.data.covisibility import covisible_mask


def camera(center, yaw_deg=0.0, width=16, height=12) -> Camera:
    """A camera at `center` looking down -z (world) turned by `yaw_deg` about the vertical, OpenCV axes."""
    c, s = math.cos(math.radians(yaw_deg)), math.sin(math.radians(yaw_deg))
    turn = torch.tensor([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]], dtype=torch.float64)
    R = torch.tensor([[1.0, 0, 0], [0, -1, 0], [0, 0, -1]], dtype=torch.float64) @ turn.T  # world-to-camera
    viewmat = torch.eye(4, dtype=torch.float64)
    viewmat[:3, :3] = R
    viewmat[:3, 3] = -R @ torch.tensor(center, dtype=torch.float64)
    K = torch.tensor([[10.0, 0, width / 2], [0, 10.0, height / 2], [0, 0, 1]])
    return Camera(viewmat.float(), K, width, height)


def brute_force(test: Camera, ranges: torch.Tensor, others: list[Camera]) -> torch.Tensor:
    """Pixel by pixel in float64: the surface point (or, at inf, the direction) projected into every other view."""
    out = torch.zeros(test.height, test.width, dtype=torch.bool)
    K_inv = torch.linalg.inv(test.K.double())
    R_t = test.viewmat[:3, :3].double().T
    for v in range(test.height):
        for u in range(test.width):
            d = R_t @ (K_inv @ torch.tensor([u + 0.5, v + 0.5, 1.0], dtype=torch.float64))
            d = d / d.norm()
            r = float(ranges[v, u])
            for other in others:
                R, t = other.viewmat[:3, :3].double(), other.viewmat[:3, 3].double()
                p = R @ d if math.isinf(r) else R @ (test.center.double() + r * d) + t
                if p[2] <= 0:
                    continue
                x = other.K.double() @ (p / p[2])
                if 0 <= x[0] < other.width and 0 <= x[1] < other.height:
                    out[v, u] = True
    return out


def seabed_ranges(cam: Camera) -> torch.Tensor:
    """Ranges to the plane z = 0 (the cameras look straight down at it)."""
    return cam.center[2] / -cam.ray_directions()[..., 2]


def test_a_view_sees_itself_and_nothing_behind_it():
    test = camera([0.0, 0.0, 3.0])
    ranges = seabed_ranges(test)
    assert covisible_mask(test, ranges, [camera([0.0, 0.0, 3.0])]).all()
    assert not covisible_mask(test, ranges, [camera([0.0, 0.0, -1.0])]).any()  # below the seabed, facing down


def test_mask_matches_brute_force_projection():
    """Shifted and turned training cameras cover part of the test view; a strip of open water (inf) counts
    where a training view holds its direction, wherever that camera is."""
    test = camera([0.0, 0.0, 3.0])
    ranges = seabed_ranges(test)
    ranges[:3] = float("inf")
    others = [camera([2.5, 0.0, 3.0]), camera([-1.0, 3.0, 2.0], yaw_deg=30.0)]
    mask = covisible_mask(test, ranges, others)
    torch.testing.assert_close(mask, brute_force(test, ranges, others), rtol=0, atol=0)
    assert 0.2 < mask.float().mean() < 0.9  # a real partial cover, not all or nothing
    far_away = camera([100.0, 50.0, 3.0])  # same orientation: its view holds every direction the test view's does
    assert covisible_mask(test, torch.full_like(ranges, float("inf")), [far_away]).all()
    assert not covisible_mask(test, seabed_ranges(test), [far_away]).any()  # its seabed is elsewhere
