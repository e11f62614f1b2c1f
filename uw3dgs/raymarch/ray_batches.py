"""Random training rays drawn across the training views (TensoRF's `SimpleSampler`): every training pixel once per
epoch in a fresh random order, `num_rays` at a time; the tail of an epoch that fills no whole batch is skipped."""

from __future__ import annotations

from typing import Any

import torch
from torch import Tensor

from uw3dgs.cameras import Camera
from uw3dgs.raymarch.rays import RayBundle, pixel_directions


class RayBatcher:
    """Serves batches {'rays': RayBundle, 'image': [N, 3] pixel colours, 'pixels': [N] row-major pixel indices}
    from `images` [V, H, W, 3] (the scene's images) of the views `view_indices`, seen by `cameras` (the scene's
    cameras, one per image). The order comes from its own generator (seeded with `seed`), so drawing rays changes
    no other random stream; `state_dict` holds what a resumed run needs to draw the same rays."""

    def __init__(self, images: Tensor, cameras: list[Camera], view_indices: list[int], seed: int):
        self.images = images
        self.view_indices = torch.tensor(view_indices, dtype=torch.long)
        self.height, self.width = int(images.shape[1]), int(images.shape[2])
        self.K = torch.stack([cameras[i].K for i in view_indices])
        self.viewmats = torch.stack([cameras[i].viewmat for i in view_indices])
        self.centers = torch.stack([cameras[i].center for i in view_indices])
        self.total = len(view_indices) * self.height * self.width
        self._generator = torch.Generator().manual_seed(seed)
        self._epoch_state = self._generator.get_state()
        self._order: Tensor | None = None
        self._cursor = 0

    def _new_epoch(self) -> None:
        self._epoch_state = self._generator.get_state()
        self._order = torch.randperm(self.total, generator=self._generator)
        self._cursor = 0

    def next(self, num_rays: int) -> dict[str, Any]:
        if num_rays > self.total:
            raise ValueError(f"a batch of {num_rays} rays is larger than the {self.total} training pixels; lower the "
                             "method's rays per batch (e.g. --model.batch-size)")
        if self._order is None or self._cursor + num_rays > self.total:
            self._new_epoch()
        ids = self._order[self._cursor:self._cursor + num_rays].to(self.images.device)
        self._cursor += num_rays
        pixels_per_view = self.height * self.width
        local = torch.div(ids, pixels_per_view, rounding_mode="floor")
        pixels = ids % pixels_per_view
        views = self.view_indices.to(ids.device)[local]
        colors = self.images[views, torch.div(pixels, self.width, rounding_mode="floor"), pixels % self.width]
        directions = pixel_directions(self.K[local], self.viewmats[local], pixels, self.width)
        origins = self.centers[local].to(directions.dtype)
        return {"rays": RayBundle(origins, directions, views), "image": colors, "pixels": pixels}

    def state_dict(self) -> dict[str, Any]:
        """The generator as it was when this epoch's order was drawn, and the position in that order."""
        return {"epoch_generator": self._epoch_state, "cursor": self._cursor, "started": self._order is not None}

    def load_state_dict(self, state: dict[str, Any]) -> None:
        self._generator.set_state(state["epoch_generator"])
        if state["started"]:
            self._new_epoch()  # draws the same order again and leaves the generator where it was
            self._cursor = int(state["cursor"])
        else:
            self._epoch_state, self._order, self._cursor = self._generator.get_state(), None, 0
