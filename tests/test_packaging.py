"""The wheel installs only the `uw3dgs` package, and third-party plugins show up through entry points."""

from __future__ import annotations

import json
import os
import subprocess
import sys
import sysconfig
import textwrap
import zipfile
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]

pytestmark = pytest.mark.slow


def run(cmd: list[str], **kwargs) -> subprocess.CompletedProcess:
    env = {k: v for k, v in os.environ.items() if k != "PYTHONPATH"}
    return subprocess.run(cmd, capture_output=True, text=True, env=env, check=True, **kwargs)


@pytest.fixture(scope="module")
def wheel(tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("dist")
    run([sys.executable, "-m", "pip", "wheel", "--no-deps", "--no-build-isolation", "-w", str(out), str(ROOT)])
    (path,) = out.glob("uw3dgs-*.whl")
    return path


@pytest.fixture(scope="module")
def fresh_venv(tmp_path_factory, wheel) -> Path:
    """A new venv holding the wheel; its dependencies (torch, ...) come from this environment's
    site-packages through a .pth path entry, so nothing is downloaded and nothing editable leaks in."""
    venv = tmp_path_factory.mktemp("venv")
    run([sys.executable, "-m", "venv", str(venv)])
    site = next((venv / "lib").glob("python3*/site-packages"))
    (site / "deps.pth").write_text(sysconfig.get_paths()["purelib"] + "\n")
    run([str(venv / "bin" / "python"), "-m", "pip", "install", "--no-deps", "--no-index", str(wheel)])
    return venv


def test_wheel_holds_only_the_uw3dgs_package(wheel):
    names = zipfile.ZipFile(wheel).namelist()
    top = {n.split("/")[0] for n in names}
    assert top == {"uw3dgs", f"{wheel.name.split('-')[0]}-{wheel.name.split('-')[1]}.dist-info"}
    for sub in ("methods", "datamanagers", "fields", "configs"):
        assert any(n.startswith(f"uw3dgs/{sub}/") for n in names), sub
    for grid in ROOT.glob("configs/*.yaml"):
        assert f"uw3dgs/configs/{grid.name}" in names
    from uw3dgs.kernels.build import HEADERS, SOURCES

    assert HEADERS
    for source in [*SOURCES, *HEADERS]:  # the compiled CPU kernels build from these on first use
        assert f"uw3dgs/kernels/{source.name}" in names


def test_every_source_package_is_packaged():
    """pyproject lists packages explicitly (folders are remapped); a new subfolder must be added there."""
    text = (ROOT / "pyproject.toml").read_text()
    roots = {"uw3dgs": "uw3dgs", "methods": "uw3dgs.methods", "datamanagers": "uw3dgs.datamanagers",
             "fields": "uw3dgs.fields", "configs": "uw3dgs.configs"}
    for folder, package in roots.items():
        for init in (ROOT / folder).rglob("__init__.py"):
            rel = init.parent.relative_to(ROOT / folder).parts
            assert f'"{".".join([package, *rel])}"' in text, f"{init.parent} is missing from pyproject packages"


def test_fresh_venv_lists_methods_without_generic_top_level_names(fresh_venv):
    out = run([str(fresh_venv / "bin" / "uw-train"), "--help"], cwd="/").stdout
    assert "3dgs" in out
    probe = ("import importlib.util as u; "
             "print([m for m in ('methods', 'fields', 'datamanagers', 'configs') if u.find_spec(m)])")
    assert run([str(fresh_venv / "bin" / "python"), "-c", probe], cwd="/").stdout.strip() == "[]"


def test_fresh_venv_runs_the_installed_demo_grid_by_name(fresh_venv, tmp_path):
    out = run([str(fresh_venv / "bin" / "uw-bench"), "demo", "--dry-run"], cwd=tmp_path)
    assert "2 cells in outputs/bench/demo: 2 new" in out.stderr and out.stdout.count("uw-train ") == 2


def install_plugin(venv: Path, tmp_path: Path, module: str, source: str, group: str, entry: str) -> None:
    """Build a one-module package whose entry point `entry` ("name = module:attr") is in `group` with this
    environment's setuptools, and install it into `venv` as a wheel."""
    plugin = tmp_path / module
    (plugin / module).mkdir(parents=True)
    (plugin / module / "__init__.py").write_text(textwrap.dedent(source))
    (plugin / "pyproject.toml").write_text(textwrap.dedent(f"""
        [build-system]
        requires = ["setuptools"]
        build-backend = "setuptools.build_meta"
        [project]
        name = "{module.replace('_', '-')}"
        version = "0.0.1"
        [project.entry-points."{group}"]
        {entry}
    """))
    run([sys.executable, "-m", "pip", "wheel", "--no-deps", "--no-build-isolation", "-w", str(tmp_path), str(plugin)])
    (plugin_wheel,) = tmp_path.glob(f"{module}-*.whl")
    run([str(venv / "bin" / "python"), "-m", "pip", "install", "--no-deps", "--no-index", str(plugin_wheel)])


def test_third_party_plugin_method_appears(fresh_venv, tmp_path):
    install_plugin(fresh_venv, tmp_path, "uw3dgs_plugin_demo", """
        import dataclasses
        from uw3dgs.methods.gaussian_splatting import method as gaussian_splatting
        from uw3dgs.registry import MethodSpec

        base = gaussian_splatting.config
        method = MethodSpec("demo-plugin-method", "A method from a third-party package.",
                            dataclasses.replace(base, method_name="demo-plugin-method", max_num_iterations=7))
    """, "uw3dgs.methods", "demo = \"uw3dgs_plugin_demo:method\"")
    uw_train = str(fresh_venv / "bin" / "uw-train")
    assert "demo-plugin-method" in run([uw_train, "--help"], cwd="/").stdout
    assert "(default: 7)" in run([uw_train, "demo-plugin-method", "--help"], cwd="/").stdout


def test_third_party_field_plugin_is_a_subcommand_and_exports_renders_and_shows(fresh_venv, tmp_path):
    """A medium field from another package, registered through the `uw3dgs.fields` entry point, with a class of its
    own that varies in space: its knobs in `uw-train uw3dgs NAME --help`, a run trains with it
    and records it, and uw-export, uw-render and the viewer serve it through the framework's interfaces alone."""
    install_plugin(fresh_venv, tmp_path, "uw3dgs_field_demo", """
        from dataclasses import dataclass

        import torch

        from uw3dgs.config import Target, target
        from uw3dgs.fields.medium import HomogeneousMedium, HomogeneousMediumConfig
        from uw3dgs.registry import FieldSpec


        class LayeredWater(HomogeneousMedium):
            \"\"\"Murkier towards +z inside the unit box.\"\"\"

            def box(self):
                return -torch.ones(3), torch.ones(3)

            def betas(self, x):
                beta_d, beta_b = super().betas(x)
                factor = 1.0 + 0.5 * torch.sigmoid(x[:, 2:3])
                return beta_d * factor, beta_b * factor


        @dataclass(frozen=True)
        class ClearWaterConfig(HomogeneousMediumConfig):
            _target: Target = target(lambda: LayeredWater)
            turbidity_note: str = "clear"
            \"\"\"A knob only this field has.\"\"\"

        field = FieldSpec("demo-clear-water", "Layered water (a plugin)", ClearWaterConfig(), kind="medium")
    """, "uw3dgs.fields", "demo-clear-water = \"uw3dgs_field_demo:field\"")
    bin_dir = fresh_venv / "bin"
    chosen = ["uw3dgs", "demo-clear-water"]
    assert "--model.medium.turbidity-note" in run([str(bin_dir / "uw-train"), *chosen, "--help"], cwd="/").stdout
    # the PyTorch paths of every kernel: the venv's own copy of the kernel sources (another path than the session's
    # build) would otherwise be compiled again, minutes on a 2-core machine, for what this test does not check
    args = [*chosen, "--max-num-iterations", "2", "--steps-per-save", "2", "--no-progress", "--model.raster.backend",
            "torch", "--model.kernels", "torch", "--output-dir", str(tmp_path / "out"), "--timestamp", "t", "synthetic",
            "--datamanager.scene.width", "32", "--datamanager.scene.height", "24", "--datamanager.scene.num-views",
            "9", "--datamanager.cache-dir", str(tmp_path / "cache")]
    run([str(bin_dir / "uw-train"), *args], cwd="/")
    config = tmp_path / "out" / "synthetic" / "uw3dgs" / "t" / "config.yml"
    saved = config.read_text()
    assert "_type: uw3dgs_field_demo.ClearWaterConfig" in saved
    run([str(bin_dir / "uw-export"), str(config), "--output", str(tmp_path / "scene.ply"), "--medium-samples", "3"],
        cwd="/")
    medium = json.loads((tmp_path / "scene.medium.json").read_text())  # named after the PLY
    assert medium["kind"] == "grid" and medium["shape"] == [3, 3, 3]
    run([str(bin_dir / "uw-render"), str(config), "--path", "test", "--outputs", "uwi,uri,backscatter", "--images",
         str(tmp_path / "frames")], cwd="/")
    assert list((tmp_path / "frames").glob("*.png"))
    shown = run([str(bin_dir / "python"), "-c", f"""
from uw3dgs.engine.evaluator import load_trained
from uw3dgs.viewer.render import MEDIUM_OUTPUTS, available_outputs, render_image
_, datamanager, model, _ = load_trained({str(config)!r}, "cpu")
assert available_outputs(model) == MEDIUM_OUTPUTS
for output in MEDIUM_OUTPUTS:
    assert render_image(model, datamanager.scene.cameras[0], output).shape == (24, 32, 3)
print("viewer ok")
"""], cwd="/")
    assert "viewer ok" in shown.stdout
