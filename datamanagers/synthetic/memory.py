"""Whether a synthetic scene fits in memory, checked before it is generated: a typo such as `--width 100000` must be
a one-line refusal, not minutes of swapping ended by the kernel's out-of-memory killer.

The estimate is a lower bound of the generator's peak memory (measured with tracemalloc on scenes of 48x36 to
480x360 pixels, 4 to 12 views, supersample 1 and 2, terrain resolutions 0.02 and 0.1): the terrain grid, the views
it keeps until they are written, and the rays of the view being ray cast."""

from __future__ import annotations

import os
from typing import Any

TERRAIN_BYTES_PER_CELL = 160
"""Height, colour, normal and material maps of one terrain grid cell."""
VIEW_BYTES_PER_PIXEL = 70
"""Images, ranges and ground truth of one kept view's pixel."""
RAY_BYTES_PER_MARCH_STEP = 6
"""The ray march's arrays, per ray (supersampled pixel) and march step."""


def memory_estimate(config: Any) -> int:
    """Bytes the generator needs at least for `config` (a SyntheticSceneConfig)."""
    cells = (config.terrain_size / config.terrain_resolution) ** 2
    pixels = config.width * config.height
    rays = pixels * config.supersample ** 2
    return int(TERRAIN_BYTES_PER_CELL * cells + VIEW_BYTES_PER_PIXEL * pixels * config.num_views
               + RAY_BYTES_PER_MARCH_STEP * rays * config.march_steps)


def available_memory() -> int | None:
    """Bytes of memory available to a new allocation (Linux: MemAvailable), None where unknown."""
    try:
        with open("/proc/meminfo") as f:
            for line in f:
                if line.startswith("MemAvailable:"):
                    return int(line.split()[1]) * 1024
    except (OSError, ValueError, IndexError):
        pass
    try:
        return os.sysconf("SC_AVPHYS_PAGES") * os.sysconf("SC_PAGE_SIZE")
    except (ValueError, OSError, AttributeError):
        return None


def check_memory(config: Any) -> None:
    """ValueError naming the options when the scene cannot fit in the memory available now."""
    need, have = memory_estimate(config), available_memory()
    if have is not None and need > have:
        raise ValueError(f"this scene needs at least {need / 2**30:.1f} GiB of memory (--width {config.width} x "
                         f"--height {config.height} x --num-views {config.num_views}, --supersample "
                         f"{config.supersample}, --terrain-size / --terrain-resolution "
                         f"{config.terrain_size / config.terrain_resolution:,.0f} cells a side) and "
                         f"{have / 2**30:.1f} GiB are available; choose a smaller scene")
