"""Does PAUP's score single out the floaters? How m, PUS, U and P of a trained `uw3dgs` run rank its floaters.

    python benchmarks/analysis/paup_scores.py outputs/synthetic/uw3dgs/<timestamp>/config.yml [--step N]

For each set of floaters, counted over the training views as `uw-eval`'s `floater_ratio` counts them
(uw3dgs/metrics/floaters.py): big and floating against the rendered surface (the Gaussians `floater_ratio`
counts), floating of any size, and the same against the true surface where the scene knows it (synthetic), it
prints how many there are, the ROC AUC of m, PUS, U and P as separators of that set from the other measured
Gaussians (1: every floater scores above every other Gaussian; 0.5: chance), how many of them the next
densification event would prune (`PAUP.candidates`), and what share of that event's Gaussians they are.
"""

from __future__ import annotations

import argparse
from pathlib import Path

import torch
from torch import Tensor

from uw3dgs.engine.evaluator import load_trained
from uw3dgs.metrics.floaters import VIEW_SHARE, floater_votes, floaters


def roc_auc(scores: Tensor, positive: Tensor) -> float | None:
    """P(score of a positive > score of a negative), ties counted one half (the Mann-Whitney U / n+ n-); None
    when either class is empty. scores [N] float, positive [N] bool."""
    pos, neg = scores[positive].double(), scores[~positive].double().sort().values
    if len(pos) == 0 or len(neg) == 0:
        return None
    below = torch.searchsorted(neg, pos, right=False).double()
    up_to = torch.searchsorted(neg, pos, right=True).double()
    return float((below + 0.5 * (up_to - below)).mean() / len(neg))


def floater_sets(model, scene, train_indices: list[int]) -> dict[str, Tensor]:
    """Name -> [N] bool, the floater sets of the module docstring."""
    with torch.no_grad():
        means, scales, _, _ = model.gaussians.activated()
        cameras = [scene.cameras[i].to(means.device) for i in train_indices]
        truth = None if scene.gt is None else [scene.gt.ranges[i] for i in train_indices]
        votes = floater_votes(means, cameras, model.render, truth)
    max_scale = scales.max(dim=-1).values
    seen = votes["seen"]
    sets = {"big, floating (floater_ratio)": floaters(max_scale, votes["floating"], seen),
            "floating, any size": (seen > 0) & (votes["floating"] >= VIEW_SHARE * seen)}
    if "floating_gt" in votes:
        sets["big, floating, true surface (floater_ratio_gt)"] = floaters(max_scale, votes["floating_gt"], seen)
        sets["floating, any size, true surface"] = (seen > 0) & (votes["floating_gt"] >= VIEW_SHARE * seen)
    return sets


def score_rows(model, scene, train_indices: list[int]) -> list[str]:
    """One Markdown row per floater set (columns as `HEADER`)."""
    paup = model.paup
    if paup is None or not paup.has_statistics:
        raise SystemExit("the run has no PAUP statistics (a uw3dgs-no-paup run, or one stopped before PAUP's start)")
    with torch.no_grad():
        pus, m = paup.scores()
        u, p = paup.filled()
        pruned = paup.candidates()
    measured = paup.measured
    rows = []
    for name, members in floater_sets(model, scene, train_indices).items():
        aucs = [roc_auc(score[measured], members[measured]) for score in (m, pus, u, p)]
        hit = int((members & pruned).sum())
        cells = [name, str(int(members.sum())), *("-" if a is None else f"{a:.2f}" for a in aucs),
                 str(hit), f"{hit / max(1, int(pruned.sum())):.1%}"]
        rows.append("| " + " | ".join(cells) + " |")
    return rows


HEADER = ("| floaters | count | AUC m | AUC PUS | AUC U | AUC P | in the next event | share of the next event |\n"
          "|---|---:|---:|---:|---:|---:|---:|---:|")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("config", type=Path, help="config.yml of a trained uw3dgs run")
    parser.add_argument("--step", type=int, default=None, help="a kept checkpoint's step (default: the latest)")
    args = parser.parse_args()
    _, datamanager, model, checkpoint = load_trained(args.config, step=args.step)
    paup = model.paup
    print(f"{checkpoint}: {model.num_gaussians} Gaussians, {int(paup.measured.sum()) if paup else 0} with "
          f"statistics; the next event would prune {int(paup.candidates().sum()) if paup else 0}")
    print(HEADER)
    print("\n".join(score_rows(model, datamanager.scene, datamanager.train_indices)))


if __name__ == "__main__":
    main()
