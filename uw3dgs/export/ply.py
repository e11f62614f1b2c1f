"""The Gaussians of a trained model in the PLY layout of the 3DGS reference code (`GaussianModel.save_ply`), which
3DGS viewers load (SIBR, SuperSplat, antimatter15/splat, gsplat's and nerfstudio's importers):

    x, y, z, nx, ny, nz, f_dc_0..2, f_rest_0..44, opacity, scale_0..2, rot_0..3      (float32 each, little endian)

with the 3DGS activations left to the reader: `opacity` is the logit (sigmoid gives the opacity), `scale_*` the
natural log of the standard deviations (exp gives them), `rot_*` the quaternion (w, x, y, z), not normalised; the
normals are zero. `f_dc_*` are the degree-0 SH coefficients per channel, `f_rest_*` the 15 higher ones channel by
channel (f_rest_0..14 red, 15..29 green, 30..44 blue), the colour being max(SH expansion + 0.5, 0) with the real SH
basis of 3DGS (`uw3dgs/render/sh.py`).

Positions are in the dataset's own frame (COLMAP's for COLMAP data), the scene normalisation undone: dataset =
world * dataset_scale + dataset_center; the log-scales gain log(dataset_scale), rotations are unchanged (the
normalisation has no rotation).
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import torch

from uw3dgs.utils.io import atomic_file

SH_REST = 15
"""Higher-order SH coefficients per channel in the layout (degree 3); a model of lower degree is padded with 0."""
PROPERTIES = (
    ["x", "y", "z", "nx", "ny", "nz"] + [f"f_dc_{i}" for i in range(3)] + [f"f_rest_{i}" for i in range(3 * SH_REST)]
    + ["opacity"] + [f"scale_{i}" for i in range(3)] + [f"rot_{i}" for i in range(4)])
"""The vertex properties, in order."""


@torch.no_grad()
def gaussian_rows(gaussians, dataset_center: tuple[float, float, float], dataset_scale: float) -> np.ndarray:
    """The PLY rows of a GaussianField (`fields/gaussians.py`), [N, 62] float32 in PROPERTIES' order, in the dataset
    frame. SH coefficients above the degree the model renders with (`active_sh_degree`) are written as 0, so a
    viewer shows what the model renders."""
    n = gaussians.num_gaussians
    means = gaussians.means.detach().double().cpu() * dataset_scale + torch.tensor(dataset_center, dtype=torch.float64)
    rest = gaussians.shN.detach().float().cpu().clone()  # [N, K, 3]: coefficient, channel
    active = int(gaussians.active_sh_degree)
    rest[:, (active + 1) ** 2 - 1:] = 0.0
    padded = torch.zeros(n, SH_REST, 3)
    padded[:, :rest.shape[1]] = rest
    columns = [
        means.float(),
        torch.zeros(n, 3),
        gaussians.sh0.detach().float().cpu()[:, 0, :],
        padded.transpose(1, 2).reshape(n, 3 * SH_REST),  # channel-major, as 3DGS flattens features_rest
        gaussians.opacities.detach().float().cpu()[:, None],
        gaussians.scales.detach().float().cpu() + math.log(dataset_scale),
        gaussians.quats.detach().float().cpu(),
    ]
    return torch.cat(columns, dim=1).numpy().astype("<f4")


def write_ply(path: Path, rows: np.ndarray) -> None:
    """Binary little-endian PLY with one `vertex` element of PROPERTIES (float), written atomically."""
    if rows.ndim != 2 or rows.shape[1] != len(PROPERTIES):
        raise ValueError(f"PLY rows must be [N, {len(PROPERTIES)}], got {list(rows.shape)}")
    header = "\n".join(["ply", "format binary_little_endian 1.0", f"element vertex {rows.shape[0]}",
                        *(f"property float {name}" for name in PROPERTIES), "end_header"]) + "\n"
    with atomic_file(path, "wb") as f:
        f.write(header.encode("ascii"))
        f.write(np.ascontiguousarray(rows, dtype="<f4").tobytes())
