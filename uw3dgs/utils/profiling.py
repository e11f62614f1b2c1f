"""Named sections of a training step, for `torch.profiler`: each is a `record_function` range named
"uw3dgs/<section>", so a trace (TensorBoard's profiler plugin, Perfetto) shows where a step goes, and
`benchmarks/speed/step_profile.py` adds up each section's forward and backward time (docs/performance.md).
Outside a profiler a section costs a few microseconds."""

from __future__ import annotations

from torch.profiler import record_function

SECTION_PREFIX = "uw3dgs/"


def section(name: str) -> record_function:
    """A context manager (or decorator) marking the work inside as section `name` of the step."""
    return record_function(SECTION_PREFIX + name)
