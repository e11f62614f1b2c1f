"""One view of a trained model as an image, with the water control (`uw3dgs.medium.formation`).

The model is asked through the framework's interface (`Model.render_view`, `Model.veiling_light`), never by its
class: any method plugin shows here, with the water control where it forms its image through the medium.
"""

from __future__ import annotations

from typing import Any

import numpy as np
import torch
from torch import Tensor

from uw3dgs.cameras import Camera
from uw3dgs.medium.formation import Water
from uw3dgs.utils.visualize import depth_to_image

MEDIUM_OUTPUTS = ("UWI", "URI", "depth", "attenuation", "backscatter")
"""What the output switch offers for a model with a medium: the underwater image, the water-free one, the range
(turbo, near = red), and the formation's two terms exp(-k beta_D z) and B (...) as RGB images."""
PLAIN_OUTPUTS = ("RGB", "depth")
"""... and for a model without one (3dgs, uw3dgs-no-medium)."""
KEYS = {"UWI": "rgb", "RGB": "rgb", "URI": "uri", "attenuation": "attenuation", "backscatter": "backscatter"}
"""Output switch label -> `Model.render_view` key."""


def has_medium(model: Any) -> bool:
    """Whether the model renders water through the formation model (it has a water control)."""
    return model.veiling_light() is not None


def available_outputs(model: Any) -> tuple[str, ...]:
    return MEDIUM_OUTPUTS if has_medium(model) else PLAIN_OUTPUTS


def learned_b_inf(model: Any) -> tuple[float, float, float] | None:
    """The model's B_inf (RGB), None without a medium."""
    light = model.veiling_light()
    if light is None:
        return None
    r, g, b = (float(x) for x in light.detach().cpu().clamp(0, 1))
    return r, g, b


@torch.no_grad()
def render_outputs(model: Any, camera: Camera, water: Water = Water()) -> dict[str, Tensor]:
    """`model.render_view(camera, water)` without gradient and without touching the torch RNG (a training run's
    draws stay its own while the viewer renders)."""
    with torch.random.fork_rng(devices=[camera.viewmat.device] if camera.viewmat.device.type == "cuda" else []):
        return model.render_view(camera, water if has_medium(model) else None)


def to_image(outputs: dict[str, Tensor], output: str) -> np.ndarray:
    """The output switch's choice as an image [H, W, 3] uint8 (colours clipped to [0, 1])."""
    if output == "depth":
        image = depth_to_image(outputs["range"], outputs["alpha"])
    elif output in KEYS and KEYS[output] in outputs:
        image = outputs[KEYS[output]]
    else:
        raise ValueError(f"unknown output {output!r}; this model has {', '.join(sorted(outputs))}")
    return (image.detach().float().clamp(0, 1) * 255 + 0.5).to(torch.uint8).cpu().numpy()


def render_image(model: Any, camera: Camera, output: str, water: Water = Water()) -> np.ndarray:
    """`render_outputs` then `to_image`: what the viewer shows, [H, W, 3] uint8."""
    return to_image(render_outputs(model, camera, water), output)
