"""Shared fixtures: a tiny synthetic scene and a fast 3DGS config, so end-to-end tests take seconds."""

from __future__ import annotations

import dataclasses
import inspect
import os
import re
import time
from pathlib import Path

import pytest
import torch

from uw3dgs.data.cache import default_cache_dir
from uw3dgs.datamanagers.synthetic import SyntheticDataManagerConfig
from uw3dgs.datamanagers.synthetic.config import SyntheticSceneConfig
from uw3dgs.engine.config import TrainConfig
from uw3dgs.engine.trainer import Trainer
from uw3dgs.methods.gaussian_splatting import method as gaussian_splatting
from uw3dgs.registry import METHODS

torch.set_num_threads(2)
# Every process a test starts (uw-train, a grid's cells, uw-render, ...) loads the compiled kernels this session
# builds, whatever UW3DGS_CACHE the test gives it, instead of building them again in the test's own cache folder
# (minutes on a 2-core machine, inside the test's time limits).
os.environ.setdefault("TORCH_EXTENSIONS_DIR", str(default_cache_dir() / "torch_extensions"))


@pytest.fixture(scope="session")
def cache_dir(tmp_path_factory) -> Path:
    return tmp_path_factory.mktemp("cache")


@pytest.fixture(scope="session")
def tiny_scene_config() -> SyntheticSceneConfig:
    return SyntheticSceneConfig(width=48, height=36, num_views=12)


def tiny_train_config(output_dir: Path, cache_dir: Path, scene: SyntheticSceneConfig, steps: int = 40,
                      reset_opacity_every: int = 0, **overrides) -> TrainConfig:
    """3DGS with every schedule shrunk to tens of steps (densify from step 10 every 10)."""
    base: TrainConfig = gaussian_splatting.config
    model = base.model
    model = dataclasses.replace(model, densification=dataclasses.replace(
        model.densification, refine_start=10, refine_every=10, reset_opacity_every=reset_opacity_every),
        gaussians=dataclasses.replace(model.gaussians, sh_degree_interval=10))
    return dataclasses.replace(
        base, model=model, max_num_iterations=steps, output_dir=output_dir, progress=False, device="cpu",
        steps_per_save=20, steps_per_eval_image=20, steps_per_eval_all_images=20,
        datamanager=SyntheticDataManagerConfig(scene=scene, cache_dir=cache_dir), **overrides)


QUICK_REPORT = {"resamples": 5, "steps": 60, "max_observations": 4000}
"""The medium report's bootstrap at the sizes tests/test_medium_estimate.py checks it with: the report every uw3dgs run
prints and saves at its start (not what the end-to-end tests check) in a third of the time on the tiny scene."""
QUICK_REPORT_ARGS = [f"--model.medium.identifiability.{k.replace('_', '-')}={v}" for k, v in QUICK_REPORT.items()]
"""The same as uw-train options."""


def as_uw3dgs(base: TrainConfig, name: str = "uw3dgs") -> TrainConfig:
    """`base` (a `tiny_train_config`) as a run of `name` (uw3dgs or a variant): the method's model and optimizers,
    base's shrunk schedules, the QUICK_REPORT medium report."""
    spec = METHODS[name].config
    medium = spec.model.medium
    medium = dataclasses.replace(medium, identifiability=dataclasses.replace(medium.identifiability, **QUICK_REPORT))
    model = dataclasses.replace(spec.model, densification=base.model.densification, gaussians=base.model.gaussians,
                                medium=medium)
    return dataclasses.replace(base, method_name=name, model=model, optimizers=spec.optimizers)


@pytest.fixture(scope="session")
def tiny_uw3dgs_trainer(tmp_path_factory, cache_dir, tiny_scene_config) -> Trainer:
    """A finished 20-step uw3dgs run on the tiny scene, trained once for the tests that read it (export, viewer, the
    benchmark scripts). A test that changes its model or folder puts them back."""
    base = tiny_train_config(tmp_path_factory.mktemp("uw3dgs-run"), cache_dir, tiny_scene_config, steps=20)
    return train(as_uw3dgs(base))


@pytest.fixture
def make_config(tmp_path, cache_dir, tiny_scene_config):
    def make(steps: int = 40, reset_opacity_every: int = 0, **overrides) -> TrainConfig:
        return tiny_train_config(tmp_path / "outputs", cache_dir, tiny_scene_config, steps, reset_opacity_every,
                                 **overrides)
    return make


def train(config: TrainConfig) -> Trainer:
    """Set up and train a run to its end."""
    trainer = Trainer(config)
    trainer.setup()
    trainer.train()
    return trainer


def train_until_killed(config: TrainConfig, monkeypatch, step: int) -> Trainer:
    """Set up and train a run that is killed (KeyboardInterrupt) as step `step` begins; the loop is restored."""
    trainer = Trainer(config)
    trainer.setup()
    original = Trainer.train_step

    def dies(self, current):
        if current == step:
            raise KeyboardInterrupt  # the process is killed mid-run
        return original(self, current)

    monkeypatch.setattr(Trainer, "train_step", dies)
    with pytest.raises(KeyboardInterrupt):
        trainer.train()
    monkeypatch.setattr(Trainer, "train_step", original)
    return trainer


def run_command(entrypoint, argv: list[str], capsys) -> tuple[int, str, str]:
    """A command's entrypoint called in process: its exit status (0 when it returns), stdout (where its error line
    goes) and stderr (its messages)."""
    code = 0
    try:
        entrypoint(argv)
    except SystemExit as exit_:
        code = int(exit_.code or 0)
    captured = capsys.readouterr()
    return code, captured.out, captured.err


TRAINS = re.compile(r"\b(train|train_until_killed|Trainer|trained_run|make_run)\(|\"uw-(train|bench)\"|uw_bench|"
                    r"webdriver|fresh_venv")
"""What in a test's own source, or in a fixture it uses, marks it end-to-end: it trains a run, runs a grid, drives a
browser or builds a venv."""


def _is_end_to_end(item: pytest.Item) -> bool:
    sources = [item.function]
    for name in getattr(item, "fixturenames", ()):
        definitions = item._fixtureinfo.name2fixturedefs.get(name, ())
        sources += [d.func for d in definitions if d.baseid]  # the project's own fixtures, not pytest's
    for source in sources:
        try:
            if TRAINS.search(inspect.getsource(source)):
                return True
        except (OSError, TypeError):
            continue
    return False


def pytest_collection_modifyitems(config: pytest.Config, items: list[pytest.Item]) -> None:
    """Mark end-to-end tests `slow` (see TRAINS): `pytest -m "not slow"` is then the fast unit suite; CI and
    scripts/test.sh run both."""
    for item in items:
        if isinstance(item, pytest.Function) and "slow" not in item.keywords and _is_end_to_end(item):
            item.add_marker(pytest.mark.slow)


def pytest_addoption(parser: pytest.Parser) -> None:
    parser.addoption("--cpu-times", metavar="FILE", default=None,
                     help="append one line per test to FILE: its id, CPU seconds (this process and the child "
                          "processes it waited for), wall seconds and the 1-minute load average, tab-separated")


@pytest.hookimpl(hookwrapper=True)
def pytest_runtest_protocol(item: pytest.Item, nextitem: pytest.Item | None):
    """With --cpu-times: a test's CPU time, setup (its fixtures' training) included, which a busy machine inflates
    far less than its wall time."""
    path = item.config.getoption("--cpu-times")
    if path is None:
        yield
        return

    def cpu() -> float:
        t = os.times()
        return t.user + t.system + t.children_user + t.children_system

    cpu_start, wall_start = cpu(), time.perf_counter()
    yield
    with open(path, "a") as out:
        out.write(f"{item.nodeid}\t{cpu() - cpu_start:.2f}\t{time.perf_counter() - wall_start:.2f}\t"
                  f"{os.getloadavg()[0]:.2f}\n")
