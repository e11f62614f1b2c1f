"""The plugin boundary: the framework (`uw3dgs/`) imports no plugin package (methods, fields, datamanagers); it talks
to plugins through registries and interfaces only, so a third-party plugin can do all that ours do."""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
PLUGINS = ("uw3dgs.methods", "uw3dgs.fields", "uw3dgs.datamanagers")


def plugin_imports(path: Path) -> list[str]:
    """The imports of plugin modules in one source file, as 'line: module'."""
    found = []
    for node in ast.walk(ast.parse(path.read_text(), filename=str(path))):
        names = []
        if isinstance(node, ast.Import):
            names = [alias.name for alias in node.names]
        elif isinstance(node, ast.ImportFrom) and node.level == 0 and node.module:
            names = [node.module, *(f"{node.module}.{alias.name}" for alias in node.names)]
        found += [f"{node.lineno}: {name}" for name in names
                  if any(name == p or name.startswith(p + ".") for p in PLUGINS)]
    return found


def test_the_framework_imports_no_plugin():
    offenders = {str(path.relative_to(ROOT)): hits for path in sorted((ROOT / "uw3dgs").rglob("*.py"))
                 if (hits := plugin_imports(path))}
    assert not offenders, f"framework modules import plugin packages: {offenders}"


@pytest.mark.parametrize("source, caught", [("from uw3dgs.fields.medium import MediumGrid\n", True),
                                            ("import uw3dgs.methods.uw3dgs\n", True),
                                            ("from uw3dgs import datamanagers\n", True),
                                            ("from uw3dgs.medium.field import Medium\n", False)])
def test_the_import_check_catches_a_plugin_import(tmp_path, source, caught):
    path = tmp_path / "module.py"
    path.write_text(f"def f():\n    {source}")
    assert bool(plugin_imports(path)) == caught
