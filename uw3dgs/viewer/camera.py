"""Conversion between viser's client camera and this project's `Camera`.

viser follows the OpenCV convention too (docs of `viser.CameraHandle`: look direction +Z, up -Y): a client camera's
`wxyz` is the rotation R_world_camera of P_world = R p_camera + position, its `fov` the *vertical* field of view in
radians and `aspect` = width / height. So the camera-to-world pose is [R | position] and `Camera.viewmat` its inverse.
"""

from __future__ import annotations

import math

import numpy as np
import torch

from uw3dgs.cameras import Camera
from uw3dgs.render.camera_path import camera_to_world, matrix_to_quaternion
from uw3dgs.render.projection import quat_to_rotmat


def render_size(aspect: float, max_resolution: int) -> tuple[int, int]:
    """(width, height) in pixels of a view of `aspect` = width / height whose long side is `max_resolution`."""
    if not (math.isfinite(aspect) and aspect > 0):
        aspect = 1.0
    if aspect >= 1.0:
        return max_resolution, max(1, round(max_resolution / aspect))
    return max(1, round(max_resolution * aspect)), max_resolution


def viser_to_camera(wxyz: np.ndarray, position: np.ndarray, fov: float, aspect: float, max_resolution: int,
                    dtype: torch.dtype = torch.float32, device: torch.device | str = "cpu",
                    name: str = "viewer") -> Camera:
    """A pinhole `Camera` seen from a viser camera: `wxyz` [4] (w, x, y, z) the rotation camera-to-world (OpenCV
    axes), `position` [3] the centre (world units of the model), `fov` the vertical field of view (radians), `aspect`
    width / height. The image has its long side `max_resolution` pixels, square pixels and the principal point at
    its centre."""
    width, height = render_size(aspect, max_resolution)
    R = quat_to_rotmat(torch.as_tensor(np.asarray(wxyz, dtype=np.float64))[None])[0]
    c = torch.as_tensor(np.asarray(position, dtype=np.float64))
    view = torch.eye(4, dtype=torch.float64)
    view[:3, :3] = R.T
    view[:3, 3] = -R.T @ c
    focal = 0.5 * height / math.tan(0.5 * fov)
    K = torch.tensor([[focal, 0.0, 0.5 * width], [0.0, focal, 0.5 * height], [0.0, 0.0, 1.0]], dtype=torch.float64)
    return Camera(view.to(device=device, dtype=dtype), K.to(device=device, dtype=dtype), width, height, name)


def camera_to_viser(camera: Camera) -> tuple[np.ndarray, np.ndarray, float, float]:
    """(wxyz [4], position [3], vertical fov in radians, aspect width / height) of `camera`, for viser (frustums,
    the initial view); the inverse of `viser_to_camera` up to the image size and a centred principal point."""
    pose = camera_to_world(camera)
    wxyz = matrix_to_quaternion(pose[:3, :3]).numpy()
    fy = float(camera.K[1, 1])
    fov = 2.0 * math.atan(0.5 * camera.height / fy)
    return wxyz, pose[:3, 3].numpy(), fov, camera.width / camera.height


def up_direction(cameras: list[Camera]) -> np.ndarray:
    """The scene's up [3] (unit, world): the mean of the cameras' up axes (-y in OpenCV), or +z without cameras."""
    if not cameras:
        return np.array([0.0, 0.0, 1.0])
    ups = np.stack([-camera_to_world(c)[:3, 1].numpy() for c in cameras])
    up = ups.mean(0)
    norm = np.linalg.norm(up)
    return up / norm if norm > 1e-9 else np.array([0.0, 0.0, 1.0])
