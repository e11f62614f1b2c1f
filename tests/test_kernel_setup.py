"""The compiled CPU kernels are built or loaded in `Trainer.setup`, before the training clock starts, so a first
run's compile is not counted in train_seconds."""

from __future__ import annotations

import time

from uw3dgs.engine.trainer import Trainer
from uw3dgs.kernels import build

DELAY = 1.0
"""A stand-in for a first compile, added to the first call of the kernel loader."""


def test_the_kernels_are_ready_before_the_clock_starts(make_config, monkeypatch):
    calls: list[float] = []
    original = build.load_extension

    def slow_first(*args, **kwargs):
        if not calls:
            time.sleep(DELAY)
        calls.append(time.perf_counter())
        return original(*args, **kwargs)

    monkeypatch.setattr(build, "load_extension", slow_first)
    trainer = Trainer(make_config(steps=2))
    trainer.setup()
    assert len(calls) == 1 and trainer.kernel_seconds >= DELAY
    trainer.train()
    assert len(calls) > 1  # the renders asked again, and got the loaded module at once
