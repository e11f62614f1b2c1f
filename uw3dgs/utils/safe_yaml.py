"""The one YAML reader of uw3dgs (grid files, run folders' config.yml): PyYAML's safe loader (plain values only, no
Python tags), with three refusals PyYAML does not make, each a `YamlFileError` naming the file and the line:

- a key given twice in one mapping (PyYAML keeps the last one silently: a second `args:` or a second dataset of one
  name would replace the first);
- a file larger than `MAX_BYTES`;
- aliases that expand to more than `MAX_NODES` values (a "billion laughs" bomb: a few lines that any code walking the
  loaded data would take forever on) or that refer to themselves.

    data = load_yaml(path)          # YamlFileError (a ValueError) on any of the above, on invalid YAML, on a tag
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import Any

import yaml
from yaml.nodes import MappingNode, Node, SequenceNode

MAX_BYTES = 4 * 2**20
"""Largest YAML file read: configs and grid files are a few kilobytes."""
MAX_NODES = 100_000
"""Most values (scalars, lists, mappings) the document may hold once its aliases are expanded: a run's config.yml
holds a few hundred."""
MERGE_TAG = "tag:yaml.org,2002:merge"


class YamlFileError(ValueError):
    """A YAML file that is not read: the message names the file, the line where known, and the fix."""


def _expanded_size(node: Node, memo: dict[int, int], open_nodes: set[int], path: Path) -> int:
    """Values under `node` with every alias expanded; memoised per node, so a bomb is measured in time linear in
    its (small) node graph, and stopped once past MAX_NODES."""
    key = id(node)
    if key in memo:
        return memo[key]
    if key in open_nodes:
        raise YamlFileError(f"{path}: line {node.start_mark.line + 1}: an alias refers to the value that contains "
                            "it (a recursive structure); write the values out")
    open_nodes.add(key)
    total = 1
    if isinstance(node, SequenceNode):
        children = node.value
    elif isinstance(node, MappingNode):
        children = [n for pair in node.value for n in pair]
    else:
        children = []
    for child in children:
        total += _expanded_size(child, memo, open_nodes, path)
        if total > MAX_NODES:
            raise YamlFileError(f"{path}: its aliases expand to more than {MAX_NODES:,} values (line "
                                f"{node.start_mark.line + 1}); a config or grid file holds a few hundred: write the "
                                "values out instead of nesting aliases")
    open_nodes.discard(key)
    memo[key] = total
    return total


def _make_loader(path: Path) -> type[yaml.SafeLoader]:
    class Loader(yaml.SafeLoader):
        def construct_mapping(self, node: Node, deep: bool = False) -> dict[Any, Any]:
            if isinstance(node, MappingNode):
                seen: dict[Any, int] = {}
                for key_node, _ in node.value:
                    if key_node.tag == MERGE_TAG:
                        continue  # `<<: *defaults` merges; a key given next to it overrides the merged one
                    key, line = self.construct_object(key_node, deep=True), key_node.start_mark.line + 1
                    try:
                        first = seen.get(key)
                    except TypeError:  # an unhashable key: PyYAML's own error says so below
                        continue
                    if first is not None:
                        raise YamlFileError(f"{path}: key {key!r} is given twice in one mapping (lines {first} and "
                                            f"{line}); YAML would keep only the second: delete or rename one")
                    seen[key] = line
            return super().construct_mapping(node, deep=deep)

        def get_single_node(self) -> Node | None:
            node = super().get_single_node()
            if node is not None:
                _expanded_size(node, {}, set(), path)
            return node

    return Loader


def load_yaml(path: str | os.PathLike, text: str | None = None) -> Any:
    """The plain data of the YAML file `path` (or of `text`, named `path` in messages); YamlFileError for invalid
    YAML, a Python tag, a duplicate key, a file over MAX_BYTES or an alias bomb; OSError where it cannot be read."""
    path = Path(path)
    if text is None:
        size = path.stat().st_size
        if size > MAX_BYTES:
            raise YamlFileError(f"{path} is {size:,} bytes, more than the {MAX_BYTES:,} a config or grid file may "
                                "have; is it the file you meant?")
        try:
            text = path.read_text()
        except UnicodeDecodeError as exc:
            raise YamlFileError(f"{path} is not text ({exc.reason} at byte {exc.start}); give a YAML file") from None
    elif len(text.encode()) > MAX_BYTES:
        raise YamlFileError(f"{path}: more than the {MAX_BYTES:,} bytes a config or grid file may have")
    try:
        return yaml.load(text, Loader=_make_loader(path))  # noqa: S506 (a SafeLoader subclass)
    except YamlFileError:
        raise
    except yaml.YAMLError as exc:
        mark = getattr(exc, "problem_mark", None)
        where = f" (line {mark.line + 1})" if mark is not None else ""
        problem = getattr(exc, "problem", None) or str(exc).splitlines()[0]
        fix = "configs and grid files hold plain values only (no Python tags)" if "tag" in str(problem) else \
            "fix that line"
        raise YamlFileError(f"{path}: not valid plain YAML{where}: {problem}; {fix}") from None
    except RecursionError:
        raise YamlFileError(f"{path}: nested too deeply to read; a config or grid file is a few levels deep") from None
