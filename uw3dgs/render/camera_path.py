"""Camera paths for rendering a trained scene: a smooth path through key poses and a spiral around their mean.

Poses are camera-to-world matrices [4, 4] in the OpenCV convention of `uw3dgs.cameras` (columns of the rotation:
x right, y down, z forward, in world coordinates; the last column: the camera centre). They are computed in
float64 and become `Camera`s (world-to-camera `viewmat`) with `cameras_from_poses`.
"""

from __future__ import annotations

import math

import torch
from torch import Tensor

from uw3dgs.cameras import Camera
from uw3dgs.render.projection import quat_to_rotmat

SPIRAL_TURNS = 2
"""Turns of the spiral around the mean pose; its depth goes in and out once over them (LLFF's render path)."""

SPIRAL_RADIUS_PERCENTILE = 90.0
"""The spiral's radius along each axis of the mean pose: this percentile of the training cameras' distances from
their mean centre along that axis (LLFF's choice: a few outlying cameras do not widen it)."""

SPIRAL_MAX_DEPTH_SHARE = 0.5
"""The spiral moves along the viewing direction by at most this share of the distance to the focus point, so it
never reaches (or passes) what it looks at."""


def camera_to_world(camera: Camera) -> Tensor:
    """The camera's pose [4, 4] float64: rotation R_w2c^T, translation the camera centre."""
    view = camera.viewmat.detach().double().cpu()
    pose = torch.eye(4, dtype=torch.float64)
    pose[:3, :3] = view[:3, :3].T
    pose[:3, 3] = -view[:3, :3].T @ view[:3, 3]
    return pose


def cameras_from_poses(poses: Tensor, template: Camera, prefix: str) -> list[Camera]:
    """One `Camera` per pose [M, 4, 4] (camera-to-world), with the intrinsics and size of `template`, its dtype and
    device, named `<prefix>_<00000>` in order."""
    R, c = poses[:, :3, :3], poses[:, :3, 3]
    view = torch.eye(4, dtype=torch.float64).repeat(len(poses), 1, 1)
    view[:, :3, :3] = R.transpose(1, 2)
    view[:, :3, 3] = -(R.transpose(1, 2) @ c[..., None])[..., 0]
    view = view.to(template.viewmat)
    return [Camera(view[k], template.K.clone(), template.width, template.height, f"{prefix}_{k:05d}")
            for k in range(len(poses))]


def matrix_to_quaternion(R: Tensor) -> Tensor:
    """The unit quaternion (w, x, y, z), w >= 0, of a rotation matrix [3, 3]: the inverse of `quat_to_rotmat`.
    Float64. Shepperd's method: it divides by the largest of the four candidates, so it is exact everywhere
    (also near 180 degrees, where w is small)."""
    m = R.double()
    trace = m[0, 0] + m[1, 1] + m[2, 2]
    largest = int(torch.stack([trace, m[0, 0], m[1, 1], m[2, 2]]).argmax())
    if largest == 0:
        s = 2.0 * torch.sqrt(1.0 + trace)
        q = torch.stack([s / 4, (m[2, 1] - m[1, 2]) / s, (m[0, 2] - m[2, 0]) / s, (m[1, 0] - m[0, 1]) / s])
    elif largest == 1:
        s = 2.0 * torch.sqrt(1.0 + m[0, 0] - m[1, 1] - m[2, 2])
        q = torch.stack([(m[2, 1] - m[1, 2]) / s, s / 4, (m[0, 1] + m[1, 0]) / s, (m[0, 2] + m[2, 0]) / s])
    elif largest == 2:
        s = 2.0 * torch.sqrt(1.0 + m[1, 1] - m[0, 0] - m[2, 2])
        q = torch.stack([(m[0, 2] - m[2, 0]) / s, (m[0, 1] + m[1, 0]) / s, s / 4, (m[1, 2] + m[2, 1]) / s])
    else:
        s = 2.0 * torch.sqrt(1.0 + m[2, 2] - m[0, 0] - m[1, 1])
        q = torch.stack([(m[1, 0] - m[0, 1]) / s, (m[0, 2] + m[2, 0]) / s, (m[1, 2] + m[2, 1]) / s, s / 4])
    q = q / q.norm()
    return -q if q[0] < 0 else q


def slerp(q0: Tensor, q1: Tensor, t: float) -> Tensor:
    """Spherical linear interpolation of unit quaternions [4] at t in [0, 1], along the shorter arc (q and -q are
    the same rotation): constant angular speed, q0 at t = 0, q1 (or -q1) at t = 1."""
    dot = float(q0 @ q1)
    if dot < 0.0:
        q1, dot = -q1, -dot
    if dot > 1.0 - 1e-12:  # (nearly) the same rotation: sin(theta) ~ 0, the chord is the arc
        q = q0 + t * (q1 - q0)
        return q / q.norm()
    theta = math.acos(min(dot, 1.0))
    return (math.sin((1.0 - t) * theta) * q0 + math.sin(t * theta) * q1) / math.sin(theta)


def interpolate_poses(keys: Tensor, frames_per_view: int) -> Tensor:
    """A smooth path [(K - 1) * frames_per_view + 1, 4, 4] through the key poses `keys` [K, 4, 4] in their order:
    key k is frame k * frames_per_view exactly, with frames_per_view - 1 frames between consecutive keys.

    Positions follow a uniform Catmull-Rom spline (a cubic Hermite curve whose tangent at a key is half the
    difference of its neighbours, at the ends the difference to the one neighbour): it passes through every key
    and its velocity is continuous. Rotations are slerped between consecutive keys at the same parameter
    (constant angular speed within a segment)."""
    if frames_per_view < 1:
        raise ValueError(f"frames_per_view must be at least 1, got {frames_per_view}")
    keys = keys.double()
    if len(keys) == 1:
        return keys.clone()
    p = keys[:, :3, 3]
    tangents = torch.empty_like(p)
    tangents[1:-1] = (p[2:] - p[:-2]) / 2
    tangents[0], tangents[-1] = p[1] - p[0], p[-1] - p[-2]
    quats = [matrix_to_quaternion(pose[:3, :3]) for pose in keys]
    poses = []
    for k in range(len(keys) - 1):
        for j in range(frames_per_view):
            s = j / frames_per_view
            h00, h10, h01, h11 = 2 * s**3 - 3 * s**2 + 1, s**3 - 2 * s**2 + s, -2 * s**3 + 3 * s**2, s**3 - s**2
            pose = torch.eye(4, dtype=torch.float64)
            if j == 0:  # the key itself, bit for bit (its quaternion round trip is only accurate to ~1e-16)
                pose[:3] = keys[k, :3]
            else:
                pose[:3, 3] = h00 * p[k] + h10 * tangents[k] + h01 * p[k + 1] + h11 * tangents[k + 1]
                pose[:3, :3] = quat_to_rotmat(slerp(quats[k], quats[k + 1], s)[None])[0]
            poses.append(pose)
    last = torch.eye(4, dtype=torch.float64)
    last[:3] = keys[-1, :3]
    poses.append(last)
    return torch.stack(poses)


def look_at(position: Tensor, target: Tensor, down: Tensor) -> Tensor:
    """The pose [4, 4] at `position` [3] whose z axis points at `target` [3] and whose y axis is `down` [3] made
    orthogonal to it (no roll about the viewing direction). `down` must not be parallel to target - position."""
    z = torch.nn.functional.normalize(target - position, dim=0)
    x = torch.nn.functional.normalize(torch.linalg.cross(down, z), dim=0)
    pose = torch.eye(4, dtype=torch.float64)
    pose[:3, 0], pose[:3, 1], pose[:3, 2], pose[:3, 3] = x, torch.linalg.cross(z, x), z, position
    return pose


def mean_pose(poses: Tensor) -> Tensor:
    """The mean of poses [K, 4, 4]: at the mean centre, looking along the mean viewing direction, its y axis the
    mean down direction (made orthogonal to it)."""
    poses = poses.double()
    center = poses[:, :3, 3].mean(dim=0)
    forward = poses[:, :3, 2].mean(dim=0)
    return look_at(center, center + forward, poses[:, :3, 1].mean(dim=0))


def spiral_poses(keys: Tensor, points: Tensor, num_frames: int) -> Tensor:
    """A closed spiral [num_frames, 4, 4] around the mean of the poses `keys` [K, 4, 4], every pose looking at the
    focus point; the last frame leads back to the first (none is repeated).

    The focus point lies on the mean pose's viewing axis at the median depth (camera-space z) of the scene's
    `points` [P, 3] in front of the mean pose. In the mean pose's frame the camera moves
    (r_x cos a, r_y sin a, r_z sin(a / SPIRAL_TURNS)) for a = 2 pi SPIRAL_TURNS k / num_frames, where r_x, r_y, r_z
    are the SPIRAL_RADIUS_PERCENTILE-th percentiles of the training centres' distances from their mean along each
    axis, r_z at most SPIRAL_MAX_DEPTH_SHARE of the focus depth. Each position is then held to the training cameras'
    own distances to the focus and heights (`within_training_band`), so the spiral never dives in for close-ups or
    under the scene. Raises ValueError when no point lies in front of the mean pose (nothing to look at)."""
    if num_frames < 1:
        raise ValueError(f"num_frames must be at least 1, got {num_frames}")
    mean = mean_pose(keys)
    R, c = mean[:3, :3], mean[:3, 3]
    depths = (points.detach().double().cpu() - c) @ R[:, 2]
    depths = depths[depths > 0]
    if depths.numel() == 0:
        raise ValueError("no scene point lies in front of the mean training camera, so the spiral has nothing to "
                         "look at; use --path interpolate")
    focus_depth = float(depths.median())
    focus = c + focus_depth * R[:, 2]
    offsets = (keys.double()[:, :3, 3] - c) @ R  # the centres in the mean pose's frame
    radii = torch.quantile(offsets.abs(), SPIRAL_RADIUS_PERCENTILE / 100.0, dim=0)
    radii[2] = min(float(radii[2]), SPIRAL_MAX_DEPTH_SHARE * focus_depth)
    poses = []
    for k in range(num_frames):
        a = 2.0 * math.pi * SPIRAL_TURNS * k / num_frames
        local = radii * torch.tensor([math.cos(a), math.sin(a), math.sin(a / SPIRAL_TURNS)], dtype=torch.float64)
        position = within_training_band(c + R @ local, focus, -R[:, 1], keys.double()[:, :3, 3])
        poses.append(look_at(position, focus, R[:, 1]))
    return torch.stack(poses)


def within_training_band(position: Tensor, focus: Tensor, up: Tensor, centres: Tensor) -> Tensor:
    """`position` [3] moved to the band the training `centres` [K, 3] occupy around `focus` [3]: its distance to
    the focus clamped to theirs (min to max), its height along the unit `up` [3] over the focus clamped to theirs
    (and to that distance), its horizontal direction kept."""
    offsets = centres - focus
    distances, heights = offsets.norm(dim=-1), offsets @ up
    offset = position - focus
    distance = float(offset.norm().clamp(float(distances.min()), float(distances.max())))
    height = min(max(float(offset @ up), float(heights.min())), float(heights.max()))
    height = min(max(height, -distance), distance)  # the distance wins: it is what keeps the scene in frame
    horizontal = offset - (offset @ up) * up
    norm = float(horizontal.norm())
    if norm < 1e-12:  # straight above or below the focus: any horizontal direction
        horizontal = torch.linalg.svd(up[None])[2][1]
        norm = 1.0
    return focus + height * up + math.sqrt(max(distance**2 - height**2, 0.0)) * horizontal / norm
