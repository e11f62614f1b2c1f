"""An experiment grid (`uw-bench GRID.yaml`): methods x datasets x seeds x named variants, each cell one normal
`uw-train` run folder. This module reads the YAML and lays out the cells; running them is `cell.py`'s job.

    output_dir: outputs/bench/demo        # cells go to OUTPUT_DIR/DATASET/METHOD/[VARIANT-]s<SEED>/
    data_root: data/seathru-nerf          # optional: datasets' `data` are relative to it (uw-bench --data-root)
    methods: [3dgs, uw3dgs]
    datasets:                             # name -> what uw-train gets; {} is the built-in synthetic scene
      synthetic: {}
      IUI3-RedSea: {data: IUI3-RedSea, args: [--downscale-factor, 8]}
    seeds: [0, 1, 2]
    args: [--max-num-iterations, 6000]    # every cell's uw-train flags
    method_args:                          # optional: method -> flags after `args` (so they win), e.g. its own length
      tensorf: [--max-num-iterations, 25000]
    variants:                             # optional: name -> extra flags; each is one more row per method
      paup-attenuation: [--model.paup.attenuation-weight, 1]
    metrics: [psnr, ssim, lpips_alex]     # optional: the table's columns (default: uw-eval table's)

Flags are `uw-train` flags as typed on the command line; those of the datamanager (`--datamanager.*`) are put after
its subcommand, where uw-train reads them, so a grid lists them like any other flag.
"""

from __future__ import annotations

import itertools
import os
from dataclasses import dataclass, field
from importlib import resources
from pathlib import Path
from typing import Any

from uw3dgs.utils.safe_yaml import YamlFileError, load_yaml

GRID_KEYS = {"output_dir", "data_root", "methods", "datasets", "seeds", "args", "method_args", "variants", "metrics"}
DATASET_KEYS = {"data", "datamanager", "args"}
DATAMANAGER_FLAG = "--datamanager."


class GridError(ValueError):
    """A grid file that cannot be run: the message names the file, the key and the fix."""


@dataclass(frozen=True)
class Dataset:
    name: str
    """The table's scene name and the run's --experiment-name."""
    data: Path | None
    """--data (resolved against the grid's data_root); None: the built-in synthetic scene."""
    datamanager: str | None
    """The datamanager subcommand; None: uw-train picks it from the layout of `data`."""
    args: tuple[str, ...]


@dataclass(frozen=True)
class Cell:
    """One run of the grid: its place in the grid and the uw-train command line that makes it."""

    dataset: str
    method: str
    variant: str
    """'' for the grid's plain settings."""
    seed: int
    run_dir: Path
    argv: tuple[str, ...]
    """uw-train's arguments (no program name)."""

    @property
    def name(self) -> str:
        return f"{self.dataset}/{self.label}/s{self.seed}"

    @property
    def label(self) -> str:
        """The table's row: the method, with the variant in brackets."""
        return f"{self.method} [{self.variant}]" if self.variant else self.method


@dataclass(frozen=True)
class Grid:
    path: Path
    output_dir: Path
    methods: tuple[str, ...]
    datasets: tuple[Dataset, ...]
    seeds: tuple[int, ...]
    args: tuple[str, ...] = ()
    method_args: dict[str, tuple[str, ...]] = field(default_factory=dict)
    variants: dict[str, tuple[str, ...]] = field(default_factory=lambda: {"": ()})
    metrics: tuple[str, ...] | None = None

    def cells(self) -> list[Cell]:
        """Every cell, dataset-major (a dataset's runs finish together, so its rows of the table fill first)."""
        out = []
        for dataset, method, (variant, flags), seed in itertools.product(
                self.datasets, self.methods, self.variants.items(), self.seeds):
            folder = f"{variant}-s{seed}" if variant else f"s{seed}"
            run_dir = self.output_dir / dataset.name / method / folder
            out.append(Cell(dataset.name, method, variant, seed, run_dir,
                            train_argv(method, dataset, (*self.args, *self.method_args.get(method, ()),
                                                         *dataset.args, *flags), seed, self.output_dir, folder)))
        return out


def select_cells(grid: Grid, methods=(), datasets=(), variants=(), seeds=()) -> list[Cell]:
    """The grid's cells with each given axis restricted to the values named (an empty axis: all of it); a value the
    grid does not have is an error naming the ones it has (a typo must not select nothing, silently)."""
    have = {"methods": tuple(grid.methods), "datasets": tuple(d.name for d in grid.datasets),
            "variants": tuple(v for v in grid.variants if v), "seeds": tuple(grid.seeds)}
    asked = {"methods": tuple(methods), "datasets": tuple(datasets), "variants": tuple(variants),
             "seeds": tuple(seeds)}
    for axis, values in asked.items():
        unknown = [v for v in values if v not in have[axis]]
        if unknown:
            raise GridError(f"{grid.path}: --{axis} {' '.join(map(str, unknown))}: not in the grid, whose {axis} are "
                            f"{', '.join(map(str, have[axis])) or 'none'}")
    return [cell for cell in grid.cells()
            if all(not asked[axis] or value in asked[axis] for axis, value in (
                ("methods", cell.method), ("datasets", cell.dataset), ("variants", cell.variant),
                ("seeds", cell.seed)))]


def train_argv(method: str, dataset: Dataset, flags: tuple[str, ...], seed: int, output_dir: Path,
               timestamp: str) -> tuple[str, ...]:
    """uw-train's arguments for one cell: the method, its flags, then the datamanager subcommand and its flags."""
    method_flags, data_flags = split_datamanager_flags(flags)
    argv = [method, *method_flags, "--seed", str(seed), "--output-dir", str(output_dir), "--experiment-name",
            dataset.name, "--timestamp", timestamp, "--no-progress"]
    if dataset.data is not None:
        argv += ["--data", str(dataset.data)]
    if data_flags and dataset.datamanager is None:
        raise GridError(f"dataset {dataset.name!r}: {data_flags[0]} is a datamanager flag; name the datamanager it "
                        "belongs to with `datamanager:` in the dataset's entry (e.g. datamanager: synthetic)")
    if dataset.datamanager is not None:
        argv.append(dataset.datamanager)
    return (*argv, *data_flags)


def split_datamanager_flags(flags: tuple[str, ...]) -> tuple[list[str], list[str]]:
    """(the flags of the method and the run, those of the datamanager): a `--datamanager.*` flag takes the values
    that follow it (up to the next flag) along."""
    method, data = [], []
    target = method
    for token in flags:
        if token.startswith("--"):
            target = data if token.startswith(DATAMANAGER_FLAG) else method
        target.append(token)
    return method, data


# ---- reading the YAML ------------------------------------------------------------------------------------------------


def _flags(value: Any, where: str, path: Path) -> tuple[str, ...]:
    if value is None:
        return ()
    if isinstance(value, str):
        return tuple(value.split())
    if not isinstance(value, list) or any(isinstance(v, (dict, list)) or v is None for v in value):
        raise GridError(f"{path}: {where} must be a list of uw-train flags and values, e.g. "
                        f"[--max-num-iterations, 6000], got {value!r}")
    return tuple(str(v).lower() if isinstance(v, bool) else str(v) for v in value)


def _names(value: Any, key: str, path: Path, kind: type) -> tuple:
    if not isinstance(value, list) or not value or not all(isinstance(v, kind) and not isinstance(v, bool)
                                                            for v in value):
        raise GridError(f"{path}: `{key}` must be a non-empty list of {kind.__name__}s, got {value!r}")
    if len(set(value)) != len(value):
        raise GridError(f"{path}: `{key}` lists an entry twice: {value!r}")
    return tuple(value)


def _seeds(value: Any, path: Path) -> tuple[int, ...]:
    from uw3dgs.engine.config import SEED_LIMIT

    seeds = _names(value, "seeds", path, int)
    bad = [s for s in seeds if not 0 <= s < SEED_LIMIT]
    if bad:
        raise GridError(f"{path}: `seeds`: {bad[0]} is not a 64-bit seed; give whole numbers from 0 to 2**64 - 1")
    return seeds


def _folder_name(name: Any, key: str, path: Path) -> str:
    if not isinstance(name, str) or name in ("", ".", "..") or "/" in name or "\\" in name:
        raise GridError(f"{path}: {key} name {name!r} must be one folder name (no '/', not empty, '.' or '..')")
    if name.startswith("."):  # hidden folders are where uw-bench keeps runs it moved aside: uw-eval table skips them
        raise GridError(f"{path}: {key} name {name!r} starts with a dot (a hidden folder, which uw-eval table does "
                        f"not search); rename it, e.g. {name.lstrip('.') or 'data'!r}")
    return name


def _dataset(name: Any, entry: Any, data_root: Path | None, path: Path) -> Dataset:
    name = _folder_name(name, "dataset", path)
    if entry is None:
        entry = {}
    if not isinstance(entry, dict) or set(entry) - DATASET_KEYS:
        raise GridError(f"{path}: dataset {name!r} must be a mapping with keys among {sorted(DATASET_KEYS)} "
                        f"({{}} is the built-in synthetic scene), got {entry!r}")
    data = entry.get("data")
    if data is not None:
        data = Path(os.path.expanduser(str(data)))
        if not data.is_absolute() and data_root is not None:
            data = data_root / data
    manager = entry.get("datamanager")
    if manager is not None and not isinstance(manager, str):
        raise GridError(f"{path}: dataset {name!r}: `datamanager` must be a name (e.g. seathru-nerf), got {manager!r}")
    return Dataset(name, data, manager, _flags(entry.get("args"), f"dataset {name!r}: `args`", path))


def preset_names() -> list[str]:
    """The grids installed with the package (configs/*.yaml)."""
    return sorted(p.name.removesuffix(".yaml") for p in resources.files("uw3dgs.configs").iterdir()
                  if p.name.endswith(".yaml"))


def find_grid(path: Path) -> Path:
    """The grid file: `path` where it exists, else, for a bare name (`demo`, `paper-table1`), the preset installed
    with the package, so a pip-installed uw3dgs runs `uw-bench demo` without a checkout."""
    path = Path(path)
    if path.exists() or path.name != str(path):
        return path
    preset = resources.files("uw3dgs.configs") / f"{path.name.removesuffix('.yaml')}.yaml"
    return Path(str(preset)) if preset.is_file() else path


def load_grid(path: Path, data_root: Path | None = None, output_dir: Path | None = None) -> Grid:
    """Read GRID.yaml (a path, or the name of a preset: `find_grid`); `data_root` and `output_dir` (the command's
    options) replace the file's. Relative paths in the file are relative to the working directory, like every
    path a user types."""
    path = find_grid(path)
    try:
        raw = load_yaml(path)
    except FileNotFoundError:
        raise FileNotFoundError(f"{path} does not exist; give a grid file, or the name of a preset: "
                                f"{', '.join(preset_names())}") from None
    except YamlFileError as exc:
        raise GridError(str(exc)) from None
    if not isinstance(raw, dict):
        raise GridError(f"{path} must be a YAML mapping with keys {sorted(GRID_KEYS)}")
    unknown = set(raw) - GRID_KEYS
    if unknown:
        raise GridError(f"{path}: unknown key(s) {sorted(unknown)}; a grid has {sorted(GRID_KEYS)}")
    for key in ("methods", "datasets", "seeds"):
        if key not in raw:
            raise GridError(f"{path}: `{key}` is missing")
    root = data_root if data_root is not None else raw.get("data_root")
    root = None if root is None else Path(os.path.expanduser(str(root)))
    out = output_dir if output_dir is not None else raw.get("output_dir")
    if out is None:
        out = Path("outputs") / "bench" / path.stem
    datasets = raw["datasets"]
    if not isinstance(datasets, dict) or not datasets:
        raise GridError(f"{path}: `datasets` must be a non-empty mapping of name -> {{data, datamanager, args}}")
    variants = raw.get("variants") or {}
    if not isinstance(variants, dict):
        raise GridError(f"{path}: `variants` must be a mapping of name -> flags, got {variants!r}")
    variants = {_folder_name(k, "variant", path): _flags(v, f"variant {k!r}", path) for k, v in variants.items()}
    method_args = raw.get("method_args") or {}
    if not isinstance(method_args, dict) or set(method_args) - set(raw["methods"] or ()):
        raise GridError(f"{path}: `method_args` must map methods of `methods` to flags, got {method_args!r}")
    metrics = raw.get("metrics")
    return Grid(
        path=path,
        output_dir=Path(os.path.expanduser(str(out))),
        methods=tuple(_folder_name(m, "method", path) for m in _names(raw["methods"], "methods", path, str)),
        datasets=tuple(_dataset(k, v, root, path) for k, v in datasets.items()),
        seeds=_seeds(raw["seeds"], path),
        args=_flags(raw.get("args"), "`args`", path),
        method_args={m: _flags(v, f"method_args {m!r}", path) for m, v in method_args.items()},
        variants=variants or {"": ()},
        metrics=None if metrics is None else _names(metrics, "metrics", path, str),
    )
