"""The wheel installs only the `uw3dgs` package, and third-party plugins show up through entry points."""

from __future__ import annotations

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


def test_third_party_plugin_method_appears(fresh_venv, tmp_path):
    plugin = tmp_path / "uw3dgs_plugin_demo"
    (plugin / "uw3dgs_plugin_demo").mkdir(parents=True)
    (plugin / "uw3dgs_plugin_demo" / "__init__.py").write_text(textwrap.dedent("""
        import dataclasses
        from uw3dgs.methods.gaussian_splatting import method as gaussian_splatting
        from uw3dgs.registry import MethodSpec

        base = gaussian_splatting.config
        method = MethodSpec("demo-plugin-method", "A method from a third-party package.",
                            dataclasses.replace(base, method_name="demo-plugin-method", max_num_iterations=7))
    """))
    (plugin / "pyproject.toml").write_text(textwrap.dedent("""
        [build-system]
        requires = ["setuptools"]
        build-backend = "setuptools.build_meta"
        [project]
        name = "uw3dgs-plugin-demo"
        version = "0.0.1"
        [project.entry-points."uw3dgs.methods"]
        demo = "uw3dgs_plugin_demo:method"
    """))
    # built with this environment's setuptools, installed into the fresh venv as a wheel
    run([sys.executable, "-m", "pip", "wheel", "--no-deps", "--no-build-isolation", "-w", str(tmp_path), str(plugin)])
    (plugin_wheel,) = tmp_path.glob("uw3dgs_plugin_demo-*.whl")
    run([str(fresh_venv / "bin" / "python"), "-m", "pip", "install", "--no-deps", "--no-index", str(plugin_wheel)])
    uw_train = str(fresh_venv / "bin" / "uw-train")
    assert "demo-plugin-method" in run([uw_train, "--help"], cwd="/").stdout
    assert "(default: 7)" in run([uw_train, "demo-plugin-method", "--help"], cwd="/").stdout
