"""Where uw3dgs keeps what it derives from datasets (generated scenes, undistorted / downscaled images)."""

from __future__ import annotations

import os
from pathlib import Path


def default_cache_dir() -> Path:
    """$UW3DGS_CACHE, else $XDG_CACHE_HOME/uw3dgs, else ~/.cache/uw3dgs."""
    if os.environ.get("UW3DGS_CACHE"):
        return Path(os.environ["UW3DGS_CACHE"])
    base = os.environ.get("XDG_CACHE_HOME") or Path.home() / ".cache"
    return Path(base) / "uw3dgs"
