"""Rendering the test views of a trained model and measuring them."""

from __future__ import annotations

import dataclasses
from pathlib import Path
from typing import Any

import torch
from rich.progress import track

from uw3dgs.config import load_config
from uw3dgs.data.datamanager import DataManager
from uw3dgs.engine.checkpoint import (
    checkpoint_path,
    checkpoint_step,
    latest_checkpoint,
    list_checkpoints,
    load_checkpoint,
    nonfinite,
)
from uw3dgs.engine.config import TrainConfig
from uw3dgs.engine.run_folder import state_problems
from uw3dgs.models.base import Model
from uw3dgs.utils.images import write_image
from uw3dgs.utils.video import labelled_row

PANEL_LABELS = {
    "gt": "photo", "render": "render", "uwi": "UWI", "uri": "URI (no water)", "depth": "range",
    "attenuation": "attenuation", "backscatter": "backscatter", "gt_clean": "clean truth",
    "uri_enhanced": "URI, PAUP-kept", "uncertainty": "PAUP uncertainty",
}
"""The label over each panel of the `compare` images, by `Model.get_image_dict` key (docs/evaluation.md says what
each shows); a key not listed is labelled with itself."""


def panel_label(key: str) -> str:
    return PANEL_LABELS.get(key, key)


@torch.no_grad()
def evaluate_views(model: Model, datamanager: DataManager, progress: bool = True,
                   save_dir: Path | None = None) -> dict[str, Any]:
    """Per-view metrics of every test view and their mean and standard deviation (per image, then averaged)."""
    was_training = model.training
    model.eval()
    per_image: list[dict[str, Any]] = []
    batches = list(datamanager.test_batches())
    for batch in track(batches, description="eval", disable=not progress):
        outputs = model.get_outputs(batch["camera"])
        name = datamanager.scene.image_names[batch["index"]]
        per_image.append({"image": name, **model.get_eval_metrics(outputs, batch)})
        if save_dir is not None:
            images = model.get_image_dict(outputs, batch)
            stem = Path(name).stem
            for key, image in images.items():
                write_image(save_dir / key / f"{stem}.png", image)
            write_image(save_dir / "compare" / f"{stem}.png",
                        labelled_row(list(images.values()), [panel_label(key) for key in images]))
            if "covisible" in batch:  # white: some training view sees it; black: no training view does
                mask = batch["covisible"].float()[..., None].expand(-1, -1, 3)
                write_image(save_dir / "covisible" / f"{stem}.png", mask)
    model.train(was_training)
    summary: dict[str, float | None] = dict(model.get_eval_summary(datamanager.scene))
    # a metric a view cannot give (no covered pixel for depth_abs_rel) is missing in that view's row (None in the
    # JSON); the mean and std are over the views that have it, and None where no view has it
    keys = [k for k in dict.fromkeys(k for row in per_image for k in row) if k != "image"]
    for row in per_image:
        for key in keys:
            row.setdefault(key, None)
    for key in keys:
        present = [row[key] for row in per_image if row[key] is not None]
        if not present:
            summary[key] = summary[f"{key}_std"] = None
            continue
        values = torch.tensor(present, dtype=torch.float64)
        summary[key] = float(values.mean())
        summary[f"{key}_std"] = float(values.std(unbiased=False))
        if len(present) < len(per_image):
            summary[f"{key}_views"] = len(present)
    return {"per_image": per_image, "summary": summary}


def load_trained(config_path: Path, device: torch.device | str = "cpu",
                 step: int | None = None) -> tuple[TrainConfig, DataManager, Model, Path]:
    """Rebuild a run from its config.yml and its latest checkpoint (or the one of `step`):
    (config, datamanager, model, checkpoint)."""
    config: TrainConfig = load_config(config_path)
    run_dir = Path(config_path).parent
    checkpoint = latest_checkpoint(run_dir) if step is None else checkpoint_path(run_dir, step)
    if checkpoint is None or not checkpoint.is_file():
        saved = ", ".join(str(checkpoint_step(p)) for p in list_checkpoints(run_dir))
        wanted = "no checkpoint" if step is None else f"no checkpoint of step {step} (saved: {saved or 'none'})"
        raise FileNotFoundError(f"{run_dir} holds {wanted} (checkpoints/step-*.ckpt); train it first, pick a saved "
                                "step, or pass another run's config.yml (--steps-per-save and --keep-checkpoints "
                                "decide which steps a run keeps)")
    config = dataclasses.replace(config, progress=False)
    datamanager = config.datamanager.setup(data=config.data, downscale_factor=config.downscale_factor,
                                           device=device, seed=config.seed)
    model = config.model.setup(scene=datamanager.scene, train_indices=datamanager.train_indices)
    state = load_checkpoint(checkpoint, "cpu")
    problems, _ = state_problems(model, state["model"])
    if problems:  # another method's (or another model size's) parameters: PyTorch's message is many lines
        shown = "; ".join(problems[:3]) + (f"; ... ({len(problems)} in all)" if len(problems) > 3 else "")
        raise ValueError(f"{checkpoint} does not hold the parameters of this run's {config.method_name} model "
                         f"[{shown}]: it was written by another method, tool or settings; pass the config.yml of the "
                         "run that wrote it")
    model.load_checkpoint_state(state["model"])
    bad = nonfinite(model.state_dict())
    if bad:  # uw3dgs never writes such a checkpoint; one from elsewhere (or an older version) is refused
        raise ValueError(f"{checkpoint}: the model's parameters {', '.join(bad)} are NaN or infinite (the run "
                         "diverged); evaluate an earlier checkpoint with --step, or train again with lower learning "
                         "rates")
    model.to(device)
    return config, datamanager, model, checkpoint
