"""Do the no-reference scores rank restorations as the clean truth does? Reads a grid's evaluated runs.

    python benchmarks/analysis/quality_ranking.py outputs/bench/underwater-quality-synthetic
    python benchmarks/analysis/quality_ranking.py outputs/bench/underwater-quality-synthetic --without uw3dgs-paper

For every run with a URI scored against a clean image (`uri_psnr`): the methods ranked by their mean over seeds of
`uri_psnr` (the truth) and of each no-reference score (`uri_uciqe`, `uri_uiqm`, higher first, as papers read them;
and their distance to the clean image's own score, nearer first), and the Spearman rank correlation of each score
with `uri_psnr` over all runs (1: the same order; 0: unrelated; -1: reversed).
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np

from uw3dgs.engine.results_table import find_runs, read_results

TRUTH = "uri_psnr"
SCORES = {"uri_uciqe": lambda r: r["uri_uciqe"], "uri_uiqm": lambda r: r["uri_uiqm"],
          "|uri_uciqe - clean_uciqe|": lambda r: -abs(r["uri_uciqe"] - r["clean_uciqe"]),
          "|uri_uiqm - clean_uiqm|": lambda r: -abs(r["uri_uiqm"] - r["clean_uiqm"])}
"""name -> how good a run is by that score (higher = better), from its results."""


def spearman(a: np.ndarray, b: np.ndarray) -> float:
    """Spearman's rho of two equal-length samples (average ranks for ties)."""
    def ranks(x: np.ndarray) -> np.ndarray:
        order = np.argsort(x, kind="stable")
        r = np.empty(len(x))
        r[order] = np.arange(len(x))
        for value in np.unique(x):  # ties share their mean rank
            r[x == value] = r[x == value].mean()
        return r
    return float(np.corrcoef(ranks(a), ranks(b))[0, 1])


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("paths", nargs="+", type=Path, help="run folders or folders holding them (a grid's output)")
    parser.add_argument("--without", nargs="*", default=[], metavar="METHOD",
                        help="leave these methods' runs out (e.g. a failed restoration that would decide the order)")
    args = parser.parse_args()
    runs = []
    for run in find_runs(args.paths)[0]:
        data = read_results(run)
        if data is not None and TRUTH in data["results"] and data["method_name"] not in args.without:
            runs.append((data["method_name"], data["results"]))
    if len(runs) < 3:
        raise SystemExit(f"{len(runs)} evaluated run(s) with {TRUTH} under {args.paths}: too few to rank")
    methods = sorted({m for m, _ in runs})
    means = {name: {m: float(np.mean([f(r) for n, r in runs if n == m])) for m in methods}
             for name, f in {TRUTH: lambda r: r[TRUTH], **SCORES}.items()}
    print(f"{len(runs)} runs, {len(methods)} methods; methods best first by the mean over their runs:")
    for name, by_method in means.items():
        order = sorted(methods, key=lambda m: -by_method[m])
        print(f"  {name:28s} " + " > ".join(f"{m} ({abs(by_method[m]):.3f})" for m in order))
    truth = np.array([r[TRUTH] for _, r in runs])
    print(f"Spearman rank correlation with {TRUTH} over the {len(runs)} runs:")
    for name, f in SCORES.items():
        print(f"  {name:28s} {spearman(np.array([f(r) for _, r in runs]), truth):+.2f}")


if __name__ == "__main__":
    main()
