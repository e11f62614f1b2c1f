"""Tables over runs (`uw-eval table`): find run folders, read their eval JSON, group the runs by scene
(`experiment_name`) and method (`method_name`), and write the mean +- std over each group's runs (seeds) per metric,
the best value of every column marked, as Markdown, LaTeX (booktabs), CSV or JSON (docs/grids.md, "Tables over
runs").

    runs = [run_from_results(path, read_results(path)) for path in find_runs([Path("outputs")])]
    table = build_table(runs, select_metrics(runs, None))
    print(render(table, "md"))

Evaluating the runs that have no results is the command's business (`uw3dgs/cli/eval.py`), not this module's.
"""

from __future__ import annotations

import csv
import dataclasses
import io
import json
import math
import statistics
from collections.abc import Iterable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Literal

from uw3dgs.engine.checkpoint import latest_checkpoint
from uw3dgs.engine.run_identity import DATA_KEY, Identity, data_differences, identity_of

RESULTS = Path("eval") / "results.json"
"""Where `uw-eval RUN/config.yml` writes a run's metrics, relative to the run folder."""
TRAIN_MINUTES = "train_minutes"
"""Derived from the results' `train_seconds` (recorded by uw-train, copied by uw-eval)."""
FORMATS = ("md", "tex", "csv", "json")
Format = Literal["md", "tex", "csv", "json"]


@dataclass(frozen=True)
class Metric:
    key: str
    label: str
    better: Literal["higher", "lower"] | None
    """Which way is best: the column's best mean is bold; None marks nothing (a share, a count, a medium value)."""
    digits: int | None = 4
    """Decimals shown; None: significant digits (`:.4g`) for keys this table does not know."""


METRICS: dict[str, Metric] = {m.key: m for m in (
    Metric("psnr", "PSNR", "higher", 2),
    Metric("ssim", "SSIM", "higher", 3),
    Metric("lpips_alex", "LPIPS", "lower", 3),
    Metric("lpips_vgg", "LPIPS-VGG", "lower", 3),
    Metric("psnr_covisible", "co-visible PSNR", "higher", 2),
    Metric("uri_psnr", "URI PSNR", "higher", 2),
    Metric("uri_ssim", "URI SSIM", "higher", 3),
    Metric("uri_lpips_alex", "URI LPIPS", "lower", 3),
    Metric("uri_lpips_vgg", "URI LPIPS-VGG", "lower", 3),
    Metric("uri_psnr_covisible", "URI co-visible PSNR", "higher", 2),
    Metric("uri_uciqe", "URI UCIQE", "higher", 3),
    Metric("uri_uiqm", "URI UIQM", "higher", 3),
    Metric("uciqe", "UCIQE", None, 3),
    Metric("uiqm", "UIQM", None, 3),
    Metric("input_uciqe", "input UCIQE", None, 3),
    Metric("input_uiqm", "input UIQM", None, 3),
    Metric("clean_uciqe", "clean UCIQE", None, 3),
    Metric("clean_uiqm", "clean UIQM", None, 3),
    Metric("depth_abs_rel", "depth AbsRel", "lower", 3),
    Metric("floater_ratio", "floater ratio", "lower", 4),
    Metric("floater_ratio_gt", "floater ratio (GT)", "lower", 4),
    Metric("b_inf_rel_error", "B_inf error", "lower", 3),
    Metric("beta_d_rel_error", "beta_D error", "lower", 3),
    Metric("beta_b_rel_error", "beta_B error", "lower", 3),
    Metric("num_gaussians", "Gaussians", "lower", 0),
    Metric(TRAIN_MINUTES, "train minutes", "lower", 1),
    Metric("train_seconds", "train seconds", "lower", 0),
    Metric("covisible_share", "co-visible share", None, 3),
    Metric("pruned_share", "pruned share", None, 4),
    Metric("train_steps", "steps", None, 0),
    Metric("num_test_views", "test views", None, 0),
)}
"""The direction table: every metric whose best is marked, and which way. Quality (PSNR, SSIM) is better higher;
errors, LPIPS, floaters, model size (Gaussians) and training time are better lower. The URI's no-reference UCIQE and
UIQM are higher-better as restoration papers read them; those of the UWI (which should match the input, not beat it),
the input and the clean image mark no best."""

DEFAULT_METRICS = ("psnr", "ssim", "lpips_alex", "uri_psnr", "floater_ratio", "num_gaussians", TRAIN_MINUTES)
"""The columns without --metrics, each dropped where no run of the table has it."""


def metric(key: str) -> Metric:
    """The table's entry for `key`, or a plain one (its label is the key, no best) for a key it does not know."""
    return METRICS.get(key) or Metric(key, key, None, None)


@dataclass(frozen=True)
class Run:
    """One evaluated run: where it is, its scene and method, and its numeric results (plus train minutes)."""

    path: Path
    scene: str
    method: str
    values: dict[str, float]
    """Numbers and infinities; a result that is neither (text, NaN) is in `unreadable`."""
    identity: Identity = Identity(None, None, None, None, None, None)
    """What it was trained and tested on (`run_identity`): runs are averaged only where it agrees."""
    unreadable: dict[str, str] = field(default_factory=dict)
    """Results that are not numbers: key -> the value as written; shown as missing, with a note."""


@dataclass(frozen=True)
class Cell:
    mean: float
    std: float | None
    """Sample standard deviation over the runs (n - 1 in the denominator); None for a single run."""
    n: int
    """How many of the group's runs have this metric."""


@dataclass
class Group:
    scene: str
    method: str
    runs: list[Run] = field(default_factory=list)
    cells: dict[str, Cell] = field(default_factory=dict)


@dataclass
class ResultsTable:
    metrics: list[Metric]
    scenes: list[str]
    methods: list[str]
    groups: dict[tuple[str, str], Group]
    best: set[tuple[str, str, str]]
    """(scene, method, metric key) of the best mean of every scene's column."""
    notes: list[str] = field(default_factory=list)
    """What the reader must know: runs shown apart because their data or lengths differ, unreadable results."""


# ---- finding and reading runs ----------------------------------------------------------------------------------------


def find_runs(paths: Sequence[Path]) -> tuple[list[Path], list[Path]]:
    """The run folders (folders holding a config.yml) named by or found (recursively) under `paths`, each once, in
    order; and the paths under which none was found. A path may be a run folder, its config.yml, or any folder
    above runs. Raises FileNotFoundError for a path that does not exist."""
    found: dict[Path, Path] = {}
    empty = []
    for path in paths:
        path = Path(path)
        if not path.exists():
            raise FileNotFoundError(f"{path} does not exist; give run folders, their config.yml, or folders holding "
                                    "runs")
        if path.is_file():
            candidates = [path] if path.name == "config.yml" else []
        else:  # folders whose name starts with a dot (temporary copies) are not searched
            candidates = [p for p in sorted(path.rglob("config.yml"))
                          if p.is_file() and not any(part.startswith(".") for part in p.relative_to(path).parts[:-1])]
        if not candidates:
            empty.append(path)
        for config in candidates:
            found.setdefault(config.parent.resolve(), config.parent)
    return list(found.values()), empty


def read_results(run_dir: Path) -> dict[str, Any] | None:
    """The run's `eval/results.json`, None where it has none; ValueError where it cannot be read as uw-eval's JSON."""
    path = Path(run_dir) / RESULTS
    if not path.is_file():
        return None
    try:
        data = json.loads(path.read_text())
    except (OSError, ValueError) as exc:
        raise ValueError(f"{path} cannot be read ({exc}); delete it to evaluate the run again") from exc
    if not (isinstance(data, dict) and isinstance(data.get("results"), dict) and data.get("method_name")):
        raise ValueError(f"{path} is not a uw-eval results file (no method_name and results); delete it to evaluate "
                         "the run again")
    return data


def stale_results(run_dir: Path, data: dict[str, Any]) -> str | None:
    """Why the results no longer describe the run (it trained on after the evaluation), or None: the checkpoint
    they evaluated is not the run's latest (a run without checkpoints keeps its results)."""
    latest = latest_checkpoint(Path(run_dir))
    evaluated = Path(str(data.get("checkpoint", ""))).name
    if latest is None:
        return None
    if evaluated != latest.name:
        return f"{Path(run_dir) / RESULTS} is of {evaluated or 'an unknown checkpoint'}, the run's latest is " \
               f"{latest.name}"
    if DATA_KEY not in data:
        return f"{Path(run_dir) / RESULTS} does not record the data it was evaluated on (an older uw-eval)"
    return None


def _number(value: Any) -> float | None:
    """A result as a number (an infinity included); None for text, null, NaN."""
    if isinstance(value, bool) or not isinstance(value, (int, float)) or math.isnan(value):
        return None
    return float(value)


def run_from_results(run_dir: Path, data: dict[str, Any]) -> Run:
    """A Run from uw-eval's JSON: every number of `results` (infinities too), plus `train_minutes` where
    `train_seconds` is known (null, absent: the run predates the record, and the value is missing, never made up);
    other values (text, NaN) are kept apart as unreadable, to be shown missing with a note."""
    values, unreadable = {}, {}
    for key, value in data["results"].items():
        number = _number(value)
        if number is not None:
            values[key] = number
        elif value is not None:
            unreadable[key] = repr(value)
    if "train_seconds" in values:
        values[TRAIN_MINUTES] = values["train_seconds"] / 60.0
    return Run(Path(run_dir), str(data.get("experiment_name") or "?"), str(data["method_name"]), values,
               identity_of(data), unreadable)


# ---- the table -------------------------------------------------------------------------------------------------------


def available_metrics(runs: Iterable[Run]) -> list[str]:
    """The metrics some run has, in the direction table's order and then by name; per-view spreads (`*_std`) and
    view counts (`*_views`) are not offered."""
    keys = {k for run in runs for k in run.values if not k.endswith(("_std", "_views"))}
    return [k for k in METRICS if k in keys] + sorted(keys - METRICS.keys())


def parse_metrics(text: str | None) -> list[str] | None:
    """`--metrics a,b,c` as a list (each once, in order); None (the default columns) without the option."""
    if text is None:
        return None
    keys = list(dict.fromkeys(k.strip() for k in text.split(",") if k.strip()))
    if not keys:
        raise ValueError(f"--metrics {text!r} names no metric; give keys separated by commas, e.g. psnr,ssim")
    return keys


def select_metrics(runs: Sequence[Run], requested: Sequence[str] | None) -> tuple[list[Metric], list[str]]:
    """The table's columns: the requested metrics (default DEFAULT_METRICS) that some run has; and the requested
    ones that are known but no run has (dropped; the default columns are dropped silently). ValueError for a
    requested key that is neither in the direction table nor in any run, naming the available ones."""
    available = available_metrics(runs)
    present = {k for run in runs for k in (*run.values, *run.unreadable)}
    if requested is None:
        return [metric(k) for k in DEFAULT_METRICS if k in present], []
    unknown = [k for k in requested if k not in METRICS and k not in present]
    if unknown:
        raise ValueError(f"--metrics: unknown metric(s) {', '.join(unknown)}; these runs have: "
                         f"{', '.join(available) or 'none'}")
    return [metric(k) for k in requested if k in present], [k for k in requested if k not in present]


def _cell(values: list[float]) -> Cell:
    """Mean and sample std of the values; with an infinity among them the mean is that infinity (or NaN for both
    signs) and there is no std."""
    if not all(math.isfinite(v) for v in values):
        return Cell(math.fsum(values), None, len(values))
    return Cell(statistics.fmean(values), statistics.stdev(values) if len(values) > 1 else None, len(values))


def separate_experiments(runs: Sequence[Run]) -> tuple[list[Run], list[str]]:
    """The runs relabelled so that a (scene, method) group holds only runs of one experiment: a scene whose runs
    differ in their data (path, content, downscale, resolution, split) becomes one column group per data, named
    after what differs ('IUI3-RedSea [downscale 8]'); a method whose runs of one scene trained for different
    numbers of steps becomes one row per length ('3dgs [2000 steps]'). Also the notes saying so."""
    notes = []
    out = list(runs)
    for scene in dict.fromkeys(run.scene for run in out):
        mine = [i for i, run in enumerate(out) if run.scene == scene]
        labels = data_differences([out[i].identity for i in mine])
        if len(labels) > 1:
            for i in mine:
                out[i] = dataclasses.replace(out[i], scene=f"{scene} [{labels[out[i].identity.data()]}]")
            notes.append(f"{scene}: its runs were trained on different data ({'; '.join(labels.values())}); each is "
                         "a column group of its own")
    for scene, method in dict.fromkeys((run.scene, run.method) for run in out):
        mine = [i for i, run in enumerate(out) if (run.scene, run.method) == (scene, method)]
        steps = list(dict.fromkeys(out[i].identity.steps for i in mine))
        if len(steps) > 1:
            for i in mine:
                length = out[i].identity.steps
                out[i] = dataclasses.replace(out[i], method=f"{method} [{'?' if length is None else length} steps]")
            notes.append(f"{scene} / {method}: runs of different lengths "
                         f"({', '.join('?' if s is None else str(s) for s in steps)} steps) are rows of their own")
    for run in out:
        for key, value in run.unreadable.items():
            notes.append(f"{run.path}: {key} is {value}, not a number: shown as missing")
    return out, notes


def _rounded(m: Metric, value: float) -> float:
    return round(value, m.digits) if m.digits is not None else float(f"{value:.4g}")


def build_table(runs: Sequence[Run], metrics: Sequence[Metric]) -> ResultsTable:
    """Group the runs by (scene, method), average every metric over each group's runs, and mark the best mean of
    every scene's column: the highest or lowest as the direction table says, compared as shown (rounded), ties all
    marked, and only where at least two methods of that scene have the metric. Runs of different data or lengths
    are never averaged (`separate_experiments`)."""
    runs, notes = separate_experiments(runs)
    groups: dict[tuple[str, str], Group] = {}
    for run in runs:
        groups.setdefault((run.scene, run.method), Group(run.scene, run.method)).runs.append(run)
    for group in groups.values():
        for m in metrics:
            values = [run.values[m.key] for run in group.runs if m.key in run.values]
            if values:
                group.cells[m.key] = _cell(values)
    scenes = sorted({scene for scene, _ in groups})
    methods = sorted({method for _, method in groups})
    best = set()
    for scene in scenes:
        for m in metrics:
            if m.better is None:
                continue
            means = {method: _rounded(m, groups[scene, method].cells[m.key].mean) for method in methods
                     if (scene, method) in groups and m.key in groups[scene, method].cells}
            if len(means) < 2:
                continue
            target = max(means.values()) if m.better == "higher" else min(means.values())
            best |= {(scene, method, m.key) for method, value in means.items() if value == target}
    return ResultsTable(list(metrics), scenes, methods, groups, best, notes)


# ---- rendering -------------------------------------------------------------------------------------------------------


def format_value(m: Metric, value: float) -> str:
    if m.digits is None:
        return f"{value:.4g}"
    if m.digits == 0:
        return f"{value:,.0f}"
    return f"{value:.{m.digits}f}"


def _cell_text(m: Metric, group: Group | None, pm: str) -> str | None:
    """'mean pm std' ('mean' for one run), with '(n=k)' where fewer than the group's runs have the metric; None for
    a missing value."""
    cell = None if group is None else group.cells.get(m.key)
    if cell is None:
        return None
    text = format_value(m, cell.mean)
    if cell.std is not None:
        text += f"{pm}{format_value(m, cell.std)}"
    if cell.n < len(group.runs):
        text += f" (n={cell.n})"
    return text


def _arrow(m: Metric, up: str, down: str) -> str:
    return {"higher": up, "lower": down}.get(m.better or "", "")


def to_markdown(table: ResultsTable) -> str:
    """A GitHub table: one row per method; per scene an `n` column and the metrics, headed `scene: metric`."""
    header = ["method"]
    for scene in table.scenes:
        header += [f"{scene}: n"] + [f"{scene}: {m.label}{_arrow(m, ' ↑', ' ↓')}" for m in table.metrics]
    lines = [_md_row(header), "|" + "|".join(["---"] + ["---:"] * (len(header) - 1)) + "|"]
    for method in table.methods:
        row = [f"`{method}`"]
        for scene in table.scenes:
            group = table.groups.get((scene, method))
            row.append(str(len(group.runs)) if group else "-")
            for m in table.metrics:
                text = _cell_text(m, group, " ± ")
                bold = (scene, method, m.key) in table.best
                row.append("-" if text is None else f"**{text}**" if bold else text)
        lines.append(_md_row(row))
    return "\n".join(lines) + "\n"


def _md_row(cells: list[str]) -> str:
    return "| " + " | ".join(c.replace("|", "\\|") for c in cells) + " |"


_TEX_SPECIAL = {"\\": r"\textbackslash{}", "&": r"\&", "%": r"\%", "$": r"\$", "#": r"\#", "_": r"\_", "{": r"\{",
                "}": r"\}", "~": r"\textasciitilde{}", "^": r"\textasciicircum{}"}


def tex_escape(text: str) -> str:
    return "".join(_TEX_SPECIAL.get(c, c) for c in text)


def to_latex(table: ResultsTable) -> str:
    """A booktabs tabular: one row per method, one \\multicolumn group per scene (`n` and the metrics), the best
    in \\textbf. Needs \\usepackage{booktabs}."""
    k = len(table.metrics) + 1
    lines = [r"\begin{tabular}{l" + "r" * (k * len(table.scenes)) + "}", r"\toprule"]
    lines.append(" & ".join([""] + [rf"\multicolumn{{{k}}}{{c}}{{{tex_escape(s)}}}" for s in table.scenes]) + r" \\")
    lines.append(" ".join(rf"\cmidrule(lr){{{2 + i * k}-{1 + (i + 1) * k}}}" for i in range(len(table.scenes))))
    labels = [r"$n$"] + [tex_escape(m.label) + _arrow(m, r"$\uparrow$", r"$\downarrow$") for m in table.metrics]
    lines.append(" & ".join(["method"] + labels * len(table.scenes)) + r" \\")
    lines.append(r"\midrule")
    for method in table.methods:
        row = [tex_escape(method)]
        for scene in table.scenes:
            group = table.groups.get((scene, method))
            row.append(str(len(group.runs)) if group else "-")
            for m in table.metrics:
                text = _cell_text(m, group, r" $\pm$ ")
                bold = (scene, method, m.key) in table.best
                row.append("-" if text is None else rf"\textbf{{{text}}}" if bold else text)
        lines.append(" & ".join(row) + r" \\")
    lines += [r"\bottomrule", r"\end{tabular}"]
    return "\n".join(lines) + "\n"


def tidy_rows(table: ResultsTable) -> list[dict[str, Any]]:
    """One row per scene x method: scene, method, n (runs), and per metric `<key>_mean`, `<key>_std`, `<key>_n`
    (None where missing)."""
    rows = []
    for (scene, method), group in sorted(table.groups.items()):
        row: dict[str, Any] = {"scene": scene, "method": method, "n": len(group.runs)}
        for m in table.metrics:
            cell = group.cells.get(m.key)
            row[f"{m.key}_mean"] = None if cell is None else cell.mean
            row[f"{m.key}_std"] = None if cell is None else cell.std
            row[f"{m.key}_n"] = 0 if cell is None else cell.n
        rows.append(row)
    return rows


def to_csv(table: ResultsTable) -> str:
    rows = tidy_rows(table)
    out = io.StringIO()
    writer = csv.DictWriter(out, fieldnames=list(rows[0]) if rows else ["scene", "method", "n"], lineterminator="\n")
    writer.writeheader()
    writer.writerows({k: "" if v is None else v for k, v in row.items()} for row in rows)
    return out.getvalue()


def to_json(table: ResultsTable) -> str:
    """The CSV's rows as a JSON list (null where missing), each with `runs`: the run folders it averages."""
    rows = tidy_rows(table)
    for row in rows:
        row["runs"] = [str(run.path) for run in table.groups[row["scene"], row["method"]].runs]
    return json.dumps(rows, indent=2) + "\n"


def render(table: ResultsTable, fmt: Format) -> str:
    """The table in `fmt`; its notes (`ResultsTable.notes`) follow a Markdown table as a list and a LaTeX one as
    comments (CSV and JSON hold the numbers only)."""
    renderers = {"md": to_markdown, "tex": to_latex, "csv": to_csv, "json": to_json}
    if fmt not in renderers:
        raise ValueError(f"--format {fmt}: one of {', '.join(FORMATS)}")
    text = renderers[fmt](table)
    if table.notes and fmt == "md":
        text += "\nNotes:\n\n" + "".join(f"- {note}\n" for note in table.notes)
    elif table.notes and fmt == "tex":
        text += "".join(f"% note: {note}\n" for note in table.notes)
    return text
