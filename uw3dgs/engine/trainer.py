"""The generic training loop. It knows no method: the model supplies parameter groups, outputs,
losses, metrics and callbacks; the config supplies learning rates and schedules."""

from __future__ import annotations

import dataclasses
import math
import time
from datetime import datetime
from pathlib import Path
from typing import Any

import torch

from uw3dgs.config import config_to_dict, save_config
from uw3dgs.data.datamanager import AutoDataManagerConfig, DataManager
from uw3dgs.engine.checkpoint import latest_checkpoint, load_checkpoint, save_checkpoint
from uw3dgs.engine.config import TrainConfig
from uw3dgs.engine.evaluator import evaluate_views
from uw3dgs.engine.optimizers import Optimizers
from uw3dgs.engine.progress import TrainingProgress
from uw3dgs.engine.writer import EventWriter
from uw3dgs.models.base import Model
from uw3dgs.utils.io import write_json


class TrainingDivergedError(RuntimeError):
    """The loss became NaN or infinite; the last checkpoint is untouched."""


def resolve_device(name: str) -> torch.device:
    if name == "auto":
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    if name == "cuda" and not torch.cuda.is_available():
        raise RuntimeError("--device cuda was asked for but PyTorch sees no CUDA device; use --device cpu")
    return torch.device(name)


def run_dir_for(config: TrainConfig, scene_name: str) -> Path:
    experiment = config.experiment_name or scene_name
    return config.output_dir / experiment / config.method_name / config.timestamp


class Trainer:
    def __init__(self, config: TrainConfig):
        if config.timestamp == "{timestamp}":
            config = dataclasses.replace(config, timestamp=datetime.now().strftime("%Y-%m-%d_%H%M%S"))
        if isinstance(config.datamanager, AutoDataManagerConfig):
            config = dataclasses.replace(config, datamanager=config.datamanager.resolve(config.data))
        self.config = config
        self.device = resolve_device(config.device)
        self.start_step = 0

    def setup(self) -> None:
        config = self.config
        torch.manual_seed(config.seed)
        self.datamanager: DataManager = config.datamanager.setup(
            data=config.data, downscale_factor=config.downscale_factor, device=self.device, seed=config.seed)
        self.run_dir = run_dir_for(config, self.datamanager.scene_name)
        checkpoint = self._checkpoint_to_resume()
        self.model: Model = config.model.setup(scene=self.datamanager.scene,
                                               train_indices=self.datamanager.train_indices)
        if checkpoint is not None:
            self.model.load_checkpoint_state(checkpoint["model"])
        self.model.to(self.device)
        if checkpoint is None:
            self.model.initialize_from_data(self.datamanager.scene, self.datamanager.train_indices)
        self.optimizers = Optimizers(config.optimizers, self.model.param_groups(), self.model.scene_extent,
                                     config.max_num_iterations)
        self.callbacks = self.model.get_training_callbacks(self.optimizers, config.max_num_iterations)
        if checkpoint is not None:
            self._restore(checkpoint)
        save_config(config, self.run_dir / "config.yml")
        scene = self.datamanager.scene
        write_json(self.run_dir / "dataparser_transforms.json",
                   {"dataset_center": list(scene.dataset_center), "dataset_scale": scene.dataset_scale,
                    "meaning": "world = (dataset - dataset_center) / dataset_scale"})
        self.writer = EventWriter(self.run_dir)

    def _checkpoint_to_resume(self) -> dict[str, Any] | None:
        if not self.config.resume:
            return None
        path = latest_checkpoint(self.run_dir)
        if path is None:
            raise FileNotFoundError(f"--resume: no checkpoint in {self.run_dir / 'checkpoints'}; pass the run's "
                                    "config with --load-config (or its --timestamp) or start without --resume")
        return load_checkpoint(path, "cpu")

    def _restore(self, checkpoint: dict[str, Any]) -> None:
        self.optimizers.load_state_dict(checkpoint["optimizers"])
        for cb in self.callbacks:
            cb.load_state_dict(checkpoint["callbacks"].get(cb.name, {}))
        self.datamanager.load_state_dict(checkpoint["datamanager"])
        torch.set_rng_state(checkpoint["rng"]["torch"])
        if torch.cuda.is_available() and "cuda" in checkpoint["rng"]:
            torch.cuda.set_rng_state_all(checkpoint["rng"]["cuda"])
        self.start_step = int(checkpoint["step"])

    def checkpoint_state(self, step: int) -> dict[str, Any]:
        rng = {"torch": torch.get_rng_state()}
        if torch.cuda.is_available():
            rng["cuda"] = torch.cuda.get_rng_state_all()
        return {"step": step, "model": self.model.state_dict(), "optimizers": self.optimizers.state_dict(),
                "callbacks": {cb.name: cb.state_dict() for cb in self.callbacks},
                "datamanager": self.datamanager.state_dict(), "rng": rng,
                "config": config_to_dict(self.config)}

    def save(self, step: int) -> Path:
        return save_checkpoint(self.run_dir, step, self.checkpoint_state(step), self.config.keep_checkpoints)

    # -- the loop --

    def train_step(self, step: int) -> tuple[dict[str, torch.Tensor], dict[str, float]]:
        for cb in self.callbacks:
            cb.before_step(step)
        self.optimizers.set_step(step)
        batch = self.datamanager.next_train()
        outputs = self.model.get_outputs(batch["camera"])
        losses = self.model.get_loss_dict(outputs, batch, step)
        loss = sum(losses.values())
        if not math.isfinite(float(loss.detach())):
            terms = {k: float(v.detach()) for k, v in losses.items()}
            raise TrainingDivergedError(
                f"step {step}: loss is {float(loss.detach())} ({terms}); nothing was "
                f"written for this step. Resume from the last checkpoint in {self.run_dir / 'checkpoints'} with "
                "--load-config <run>/config.yml --resume, after lowering the learning rates (--optimizers.*.lr)")
        self.optimizers.zero_grad()
        loss.backward()
        for cb in self.callbacks:
            cb.after_backward(step, batch, outputs)
        self.optimizers.step()
        for cb in self.callbacks:
            cb.after_step(step, batch, outputs)
        metrics = self.model.get_metrics_dict(outputs, batch)
        losses = {"loss": loss.detach(), **{k: v.detach() for k, v in losses.items()}}
        return losses, metrics

    def train(self) -> Path:
        config = self.config
        last = config.max_num_iterations
        step = self.start_step
        self.model.train()
        with TrainingProgress(config.max_num_iterations, self.start_step, enabled=config.progress) as progress:
            try:
                while step < last:
                    step += 1
                    t0 = time.perf_counter()
                    losses, metrics = self.train_step(step)
                    progress.update(step, float(losses["loss"]), metrics, time.perf_counter() - t0)
                    self._log(step, losses, metrics, progress.steps_per_second)
                    self._periodic(step, last)
            except KeyboardInterrupt:
                # a step cut in half is not a state to save: the last periodic checkpoint is
                progress.console.print(f"Interrupted at step {step}. Resume from the last checkpoint with "
                                       f"uw-train --load-config {self.run_dir / 'config.yml'} --resume")
                raise
        self.writer.close()
        return self.run_dir

    def _log(self, step: int, losses: dict[str, torch.Tensor], metrics: dict[str, float], sps: float) -> None:
        if step % self.config.steps_per_log and step != self.config.max_num_iterations:
            return
        scalars = {f"train/{k}": float(v) for k, v in {**losses, **metrics}.items()}
        scalars["train/steps_per_sec"] = sps
        for name in self.optimizers.optimizers:
            scalars[f"lr/{name}"] = self.optimizers.lr(name, step)
        self.writer.scalars(scalars, step)

    def _periodic(self, step: int, last: int) -> None:
        config = self.config
        if step % config.steps_per_eval_image == 0 and self.datamanager.test_indices:
            self._eval_one_image(step)
        if step % config.steps_per_eval_all_images == 0 or step == last:
            self.eval_all(step)
        if step % config.steps_per_save == 0 or step == last:
            self.save(step)

    @torch.no_grad()
    def _eval_one_image(self, step: int) -> None:
        index = self.datamanager.test_indices[(step // self.config.steps_per_eval_image)
                                              % len(self.datamanager.test_indices)]
        batch = self.datamanager.get_batch(index)
        self.model.eval()
        outputs = self.model.get_outputs(batch["camera"])
        self.model.train()
        for name, image in self.model.get_image_dict(outputs, batch).items():
            self.writer.image(f"eval_image/{name}", image, step)
        for name, value in self.model.get_eval_metrics(outputs, batch).items():
            self.writer.scalars({f"eval_image/{name}": value}, step)

    def eval_all(self, step: int) -> dict[str, float]:
        if not self.datamanager.test_indices:
            return {}
        summary = evaluate_views(self.model, self.datamanager, progress=False)["summary"]
        self.writer.scalars({f"eval/{k}": v for k, v in summary.items()}, step)
        return summary
