"""What a run was trained and evaluated on, so that a table averages as seeds only runs of the same experiment.

uw-eval records it in its results (`data`): the dataset's path, a fingerprint of its content as the run read it
(every image's pixels at the run's resolution and every camera), the downscale factor and resolution, and the
split (which views were trained on and which were tested). The table groups a scene's runs only where these and the
training length agree (`Identity`); where they differ the differing thing names the column group (data) or the row
(steps), so no cell ever averages two experiments.
"""

from __future__ import annotations

import hashlib
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

DATA_KEY = "data"
"""The key of the record in uw-eval's results JSON."""


def _digest(parts: list[bytes]) -> str:
    hasher = hashlib.sha256()
    for part in parts:
        hasher.update(len(part).to_bytes(8, "little"))
        hasher.update(part)
    return hasher.hexdigest()[:16]


def data_record(config: Any, datamanager: Any) -> dict[str, Any]:
    """The record of what the run was trained and tested on (see the module's docstring), JSON-ready."""
    scene = datamanager.scene
    images = scene.images.detach().cpu()
    content = [np.ascontiguousarray(images.numpy()).tobytes()]
    for camera in scene.cameras:
        content += [camera.viewmat.detach().double().cpu().numpy().tobytes(),
                    camera.K.detach().double().cpu().numpy().tobytes(), f"{camera.width}x{camera.height}".encode()]
    names = [scene.image_names[i] for i in datamanager.test_indices]
    test = datamanager.test_indices[0] if datamanager.test_indices else 0
    return {
        "path": None if config.data is None else str(Path(config.data).expanduser().resolve()),
        "fingerprint": _digest(content),
        "downscale_factor": int(config.downscale_factor),
        "resolution": [int(scene.cameras[test].width), int(scene.cameras[test].height)],
        "split": {"train_views": len(datamanager.train_indices), "test_views": len(names),
                  "fingerprint": _digest([repr(list(datamanager.train_indices)).encode(),
                                          repr(names).encode()])},
        "meaning": "what the run was trained and tested on: the dataset (path; fingerprint of every image at the "
                   "run's resolution and every camera), the downscale factor, the test views' size in pixels, and "
                   "the split; uw-eval table groups runs as seeds only where these and train_steps agree",
    }


@dataclass(frozen=True)
class Identity:
    """The parts of a run that must agree for it to be averaged with others; None where not recorded."""

    path: str | None
    fingerprint: str | None
    downscale: int | None
    resolution: tuple[int, int] | None
    split: str | None
    steps: int | None

    def data(self) -> tuple:
        return self.path, self.fingerprint, self.downscale, self.resolution, self.split


def identity_of(results: dict[str, Any]) -> Identity:
    """The identity of a run from uw-eval's JSON (`read_results`); parts it does not record are None."""
    record = results.get(DATA_KEY)
    record = record if isinstance(record, dict) else {}
    split = record.get("split") if isinstance(record.get("split"), dict) else {}
    resolution = record.get("resolution")
    steps = (results.get("results") or {}).get("train_steps")
    return Identity(
        path=record.get("path") if isinstance(record.get("path"), str) else None,
        fingerprint=record.get("fingerprint") if isinstance(record.get("fingerprint"), str) else None,
        downscale=record.get("downscale_factor") if isinstance(record.get("downscale_factor"), int) else None,
        resolution=tuple(resolution) if isinstance(resolution, list) and len(resolution) == 2 else None,
        split=split.get("fingerprint") if isinstance(split.get("fingerprint"), str) else None,
        steps=steps if isinstance(steps, int) and not isinstance(steps, bool) else None,
    )


def data_differences(identities: list[Identity]) -> dict[tuple, str]:
    """For runs of one scene name: each distinct data identity -> the words that tell it from the others ('' when
    all agree): the path where paths differ, else the fingerprint, the downscale factor, the resolution, the split,
    each only where it differs; 'not recorded' for runs whose results predate the record."""
    distinct = list(dict.fromkeys(i.data() for i in identities))
    if len(distinct) < 2:
        return {d: "" for d in distinct}
    labels = {}
    fields = list(zip(*distinct, strict=True))
    for d in distinct:
        if all(v is None for v in d):
            labels[d] = "data not recorded"
            continue
        words = []
        path, fingerprint, downscale, resolution, split = d
        if len(set(fields[0])) > 1:
            words.append(f"data {path}" if path is not None else "built-in scene")
        elif len(set(fields[1])) > 1:
            words.append(f"data fingerprint {fingerprint}")
        if len(set(fields[2])) > 1:
            words.append(f"downscale {downscale}")
        if len(set(fields[3])) > 1 and resolution is not None:
            words.append(f"{resolution[0]}x{resolution[1]} px")
        if len(set(fields[4])) > 1:
            words.append(f"split {split}")
        labels[d] = ", ".join(words) or "other data"
    return labels
