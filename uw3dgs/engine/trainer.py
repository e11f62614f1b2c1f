"""The generic training loop. It knows no method: the model supplies parameter groups, outputs,
losses, metrics and callbacks; the config supplies learning rates and schedules.

What it guarantees about the run folder, resuming, signals and diverged parameters is listed in
docs/training.md ("What is guaranteed")."""

from __future__ import annotations

import dataclasses
import json
import math
import signal
import time
from datetime import datetime
from pathlib import Path
from typing import Any

import torch

from uw3dgs.config import config_to_dict, save_config
from uw3dgs.data.datamanager import AutoDataManagerConfig, DataManager
from uw3dgs.engine.checkpoint import (
    CHECKPOINT_DIR,
    RESUME_KEYS,
    checkpoint_path,
    latest_checkpoint,
    load_checkpoint,
    nonfinite,
    save_checkpoint,
)
from uw3dgs.engine.config import TrainConfig
from uw3dgs.engine.evaluator import evaluate_views
from uw3dgs.engine.optimizers import Optimizers
from uw3dgs.engine.progress import TrainingProgress
from uw3dgs.engine.run_folder import (
    NOTES_DIR,
    RunFolderError,
    RunLock,
    check_fresh,
    remove_stale_temp_files,
    shape_mismatch,
)
from uw3dgs.engine.signals import StopRequests, TrainingInterrupted
from uw3dgs.engine.writer import EventWriter
from uw3dgs.models.base import Model
from uw3dgs.utils.io import remove_temp_files, unwritable_reason, write_json
from uw3dgs.utils.profiling import section

TRAIN_TIME_FILE = "train_time.json"
"""RUN/train_time.json: the training wall time up to each checkpoint (docs/training.md, "The run folder")."""
TRAIN_TIME_MEANING = (
    "train_seconds: wall-clock seconds of uw-train's training loop up to the checkpoint of train_steps, summed over "
    "the run's segments (a resumed run adds its own; steps redone after a kill count once, as redone); it includes "
    "the in-training evaluations, logging and checkpoint writes, not the setup (reading the data, building the "
    "model); checkpoints: the same per checkpoint step; null: not recorded (a segment from before this record)")


class TrainingDivergedError(RuntimeError):
    """The loss or a parameter became NaN or infinite; the last checkpoint is untouched."""


def resolve_device(name: str) -> torch.device:
    if name == "auto":
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    if name == "cuda" and not torch.cuda.is_available():
        raise RuntimeError("--device cuda was asked for but PyTorch sees no CUDA device; use --device cpu")
    return torch.device(name)


def prepare_kernels(model_config: Any, device: torch.device) -> float:
    """Build (first use) or load the compiled CPU kernels now, before the training clock starts, when the run will
    use them (on the CPU, with `--model.kernels compiled` or the compiled rasterizer); returns the seconds it took (0
    when not used). `train_seconds` then counts training only, not a first compile (docs/training.md, "The run
    folder")."""
    from uw3dgs.kernels import build
    from uw3dgs.render.rasterize import select_backend

    raster = getattr(model_config, "raster", None)
    compiled = getattr(model_config, "kernels", None) == "compiled" or (
        raster is not None and select_backend(raster.backend, device) == "cpu")
    if device.type != "cpu" or not compiled:
        return 0.0
    start = time.perf_counter()
    build.load_extension()
    return time.perf_counter() - start


def read_train_time(run_dir: Path) -> dict[str, Any] | None:
    """RUN/train_time.json, or None where the run has none (it predates the record) or it cannot be read."""
    try:
        data = json.loads((Path(run_dir) / TRAIN_TIME_FILE).read_text())
    except (OSError, ValueError):
        return None
    return data if isinstance(data, dict) and isinstance(data.get("checkpoints"), dict) else None


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
        self.lock: RunLock | None = None
        self._resumed_from: Path | None = None
        self._checked_step = -1
        # training wall time: the seconds of earlier segments (restored on resume; None: not recorded there), the
        # start of this process's training loop, and the seconds at each checkpoint step (RUN/train_time.json)
        self._seconds_before: float | None = 0.0
        self._segment_start: float | None = None
        self._seconds_at: dict[str, float | None] = {}

    def setup(self) -> None:
        """Read the data, take the run folder (its lock) and build or restore the model. Nothing but the lock file
        is written to the run folder before every check has passed; the lock is held until `train()` ends (or
        `close()`)."""
        config = self.config
        resume_here = config.resume and config.load_config is not None
        problem = unwritable_reason(Path(config.load_config).parent if resume_here else config.output_dir, folder=True)
        if problem is not None:  # before the data is read, which may take long
            raise RunFolderError(f"{'the run folder' if resume_here else '--output-dir'}: {problem}")
        if config.viewer:  # a port in use is reported before the data is read too
            from uw3dgs.viewer.server import check_port, require_viser

            require_viser()
            check_port(config.viewer_host, config.viewer_port, "--viewer-port")
        torch.manual_seed(config.seed)
        self.datamanager: DataManager = config.datamanager.setup(
            data=config.data, downscale_factor=config.downscale_factor, device=self.device, seed=config.seed)
        self.kernel_seconds = prepare_kernels(config.model, self.device)
        self.run_dir = self._run_dir()
        try:
            self._setup_in_run_dir()
        except BaseException:
            self.close()
            raise

    def _run_dir(self) -> Path:
        """`--resume` with `--load-config` continues the run in the folder holding that config.yml (a copied or
        moved run resumes where it is, never in the folder it was copied from); otherwise
        OUTPUT_DIR/EXPERIMENT/METHOD/TIMESTAMP."""
        if self.config.resume and self.config.load_config is not None:
            return Path(self.config.load_config).parent
        return run_dir_for(self.config, self.datamanager.scene_name)

    def _setup_in_run_dir(self) -> None:
        config = self.config
        if config.resume and not self.run_dir.is_dir():
            raise FileNotFoundError(f"--resume: no checkpoint to resume from, {self.run_dir} does not exist; pass "
                                    "the run's config with --load-config (or its --timestamp), or start without "
                                    "--resume")
        self.lock = RunLock(self.run_dir)
        self.lock.acquire()
        if not config.resume:
            check_fresh(self.run_dir)
        remove_stale_temp_files(self.run_dir)
        remove_temp_files(self.run_dir, {TRAIN_TIME_FILE})
        checkpoint = self._checkpoint_to_resume()
        self.model: Model = config.model.setup(scene=self.datamanager.scene,
                                               train_indices=self.datamanager.train_indices)
        if checkpoint is not None:
            problem = shape_mismatch(self.model, checkpoint, config, self._resumed_from)
            if problem is not None:
                raise ValueError(problem)
            self.model.load_checkpoint_state(checkpoint["model"])
            bad = nonfinite(self.model.param_groups())
            if bad:
                raise TrainingDivergedError(
                    f"{self._resumed_from}: parameters of group(s) {', '.join(bad)} are NaN or infinite; delete "
                    "this checkpoint to resume from the one before it")
        self.model.to(self.device)
        if checkpoint is None:
            self.model.initialize_from_data(self.datamanager.scene, self.datamanager.train_indices)
            for name, note in self.model.run_notes().items():
                write_json(self.run_dir / NOTES_DIR / f"{name}.json", note)
        self.optimizers = Optimizers(config.optimizers, self.model.param_groups(), self.model.scene_extent,
                                     config.max_num_iterations)
        self.callbacks = self.model.get_training_callbacks(self.optimizers, config.max_num_iterations)
        if checkpoint is not None:
            self._restore(checkpoint)
        # --resume and --load-config say how this invocation started, not what the run is: the saved config starts a
        # new run (and never points a later --resume at another folder); --viewer is how it is watched, not the run
        save_config(dataclasses.replace(config, resume=False, load_config=None, viewer=False),
                    self.run_dir / "config.yml")
        scene = self.datamanager.scene
        write_json(self.run_dir / "dataparser_transforms.json",
                   {"dataset_center": list(scene.dataset_center), "dataset_scale": scene.dataset_scale,
                    "meaning": "world = (dataset - dataset_center) / dataset_scale"})
        self.writer = EventWriter(self.run_dir)

    def close(self) -> None:
        """Release the run folder (done by `train()` when it ends, however it ends)."""
        if self.lock is not None:
            self.lock.release()

    def _checkpoint_to_resume(self) -> dict[str, Any] | None:
        if not self.config.resume:
            return None
        path = latest_checkpoint(self.run_dir)
        if path is None:
            raise FileNotFoundError(f"--resume: no checkpoint in {self.run_dir / CHECKPOINT_DIR} (the run stopped "
                                    "before its first save); start it again without --resume under another "
                                    f"--timestamp, or after deleting {self.run_dir}")
        self._resumed_from = path
        return load_checkpoint(path, "cpu", required=RESUME_KEYS)

    def _restore(self, checkpoint: dict[str, Any]) -> None:
        self.optimizers.load_state_dict(checkpoint["optimizers"])
        for cb in self.callbacks:
            cb.load_state_dict(checkpoint["callbacks"].get(cb.name, {}))
        self.datamanager.load_state_dict(checkpoint["datamanager"])
        torch.set_rng_state(checkpoint["rng"]["torch"])
        if torch.cuda.is_available() and "cuda" in checkpoint["rng"]:
            torch.cuda.set_rng_state_all(checkpoint["rng"]["cuda"])
        self.start_step = int(checkpoint["step"])
        seconds = checkpoint.get("train_seconds")  # absent in checkpoints written before the time was recorded
        self._seconds_before = None if seconds is None else float(seconds)
        earlier = (read_train_time(self.run_dir) or {}).get("checkpoints", {})
        self._seconds_at = {k: v for k, v in earlier.items() if k.isdigit() and int(k) < self.start_step}
        self._seconds_at[str(self.start_step)] = self._seconds_before

    def checkpoint_state(self, step: int) -> dict[str, Any]:
        rng = {"torch": torch.get_rng_state()}
        if torch.cuda.is_available():
            rng["cuda"] = torch.cuda.get_rng_state_all()
        return {"step": step, "model": self.model.state_dict(), "optimizers": self.optimizers.state_dict(),
                "callbacks": {cb.name: cb.state_dict() for cb in self.callbacks},
                "datamanager": self.datamanager.state_dict(), "rng": rng,
                "config": config_to_dict(self.config), "train_seconds": self.train_seconds()}

    def train_seconds(self) -> float | None:
        """Training wall time of the run so far: earlier segments (from the checkpoint resumed) plus this process's
        training loop; None where an earlier segment was not recorded."""
        if self._seconds_before is None:
            return None
        running = 0.0 if self._segment_start is None else time.perf_counter() - self._segment_start
        return self._seconds_before + running

    def save(self, step: int) -> Path:
        """Write the checkpoint of `step`, after checking that every parameter is finite (never a NaN checkpoint)."""
        self.check_parameters(step)
        state = self.checkpoint_state(step)
        path = save_checkpoint(self.run_dir, step, state, self.config.keep_checkpoints)
        # after the checkpoint: the record never names a step whose checkpoint is not on disk
        self._seconds_at[str(step)] = state["train_seconds"]
        write_json(self.run_dir / TRAIN_TIME_FILE, {
            "train_seconds": state["train_seconds"], "train_steps": step,
            "checkpoints": dict(sorted(self._seconds_at.items(), key=lambda item: int(item[0]))),
            "meaning": TRAIN_TIME_MEANING})
        return path

    def check_parameters(self, step: int) -> None:
        """Stop the run like a non-finite loss does if a parameter group holds NaN or an infinity. Run every
        --steps-per-log steps and before every evaluation and checkpoint."""
        if self._checked_step == step:
            return
        bad = nonfinite(self.model.param_groups())
        if bad:
            flags = ", ".join(f"--optimizers.{name.replace('_', '-')}.lr" for name in bad)
            raise TrainingDivergedError(
                f"step {step}: parameters of group(s) {', '.join(bad)} are NaN or infinite after the optimizer step "
                "(checked every --steps-per-log steps and before every checkpoint); nothing was written for this "
                f"step. Resume from the last checkpoint in {self.run_dir / CHECKPOINT_DIR} with --load-config "
                f"{self.run_dir / 'config.yml'} --resume, after lowering those groups' learning rates ({flags})")
        self._checked_step = step

    # -- the loop --

    def train_step(self, step: int) -> tuple[dict[str, torch.Tensor], dict[str, float]]:
        for cb in self.callbacks:
            cb.before_step(step)
        self.optimizers.set_step(step)
        rays = self.model.rays_per_batch()
        with section("data"):
            batch = self.datamanager.next_train() if rays is None else self.datamanager.next_train_rays(rays)
        outputs = self.model.get_train_outputs(batch)
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
        with section("metrics"):
            metrics = self.model.get_metrics_dict(outputs, batch)
        losses = {"loss": loss.detach(), **{k: v.detach() for k, v in losses.items()}}
        return losses, metrics

    def train(self) -> Path:
        config = self.config
        last = config.max_num_iterations
        step = self.start_step
        self.model.train()
        viewer = None
        try:
            if step >= last:  # a resumed run that is already done: not "Done" with nothing trained
                raise ValueError(f"--resume: {self._resumed_from} is at step {step} and --max-num-iterations is "
                                 f"{last}: nothing left to train; raise --max-num-iterations, or evaluate with "
                                 f"uw-eval {self.run_dir / 'config.yml'}")
            with StopRequests() as stop, TrainingProgress(config.max_num_iterations, self.start_step,
                                                          enabled=config.progress, status_dir=self.run_dir) as progress:
                viewer = self._start_viewer(progress.console)
                self._segment_start = time.perf_counter()
                try:
                    while step < last:
                        step += 1
                        t0 = time.perf_counter()
                        losses, metrics = self.train_step(step)
                        if step % config.steps_per_log == 0 or step == last:
                            self.check_parameters(step)
                        progress.update(step, float(losses["loss"]), metrics, time.perf_counter() - t0)
                        self._log(step, losses, metrics, progress.steps_per_second)
                        self._periodic(step, last)
                        if viewer is not None:  # no gradient, no RNG draw, no state change: same numbers
                            viewer.update(step)
                        if stop.signum is not None and step < last:
                            self._stop(step, stop.signum, progress.console)
                except KeyboardInterrupt:
                    # a step cut in half is not a state to save: the last periodic checkpoint is
                    progress.console.print(f"Interrupted at step {step}. Resume from the last checkpoint with "
                                           f"uw-train --load-config {self.run_dir / 'config.yml'} --resume",
                                           soft_wrap=True)
                    raise
        finally:
            if viewer is not None:
                viewer.stop()
            self.writer.close()
            self.close()
        return self.run_dir

    def _start_viewer(self, console: Any) -> Any:
        """With --viewer, the live viewer (uw3dgs/viewer/), else None."""
        if not self.config.viewer:
            return None
        from uw3dgs.viewer.server import Viewer, views_from_datamanager

        config = self.config
        viewer = Viewer(self.model, views_from_datamanager(self.datamanager), host=config.viewer_host,
                        port=config.viewer_port, live=True, port_option="--viewer-port",
                        title=f"{self.datamanager.scene_name} / {config.method_name} (training)")
        console.print(f"viewer at {viewer.url}", soft_wrap=True, highlight=False)
        return viewer

    def _stop(self, step: int, signum: int, console: Any) -> None:
        """After a complete step: its checkpoint (unless `_periodic` just wrote it), how to resume, then stop."""
        path = checkpoint_path(self.run_dir, step)
        if not path.is_file():
            path = self.save(step)
        message = (f"Stopped by {signal.Signals(signum).name} after step {step}; checkpoint {path}. Resume with: "
                   f"uw-train --load-config {self.run_dir / 'config.yml'} --resume")
        console.print(message, soft_wrap=True, highlight=False, markup=False)
        raise TrainingInterrupted(signum, step, path, message)

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
        eval_image = step % config.steps_per_eval_image == 0 and self.datamanager.test_indices
        eval_all = step % config.steps_per_eval_all_images == 0 or step == last
        save = step % config.steps_per_save == 0 or step == last
        if eval_image or eval_all or save:  # a diverged model is neither evaluated nor saved
            self.check_parameters(step)
        if eval_image:
            self._eval_one_image(step)
        if eval_all:
            self.eval_all(step)
        if save:
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
            if value is not None:
                self.writer.scalars({f"eval_image/{name}": value}, step)
        for name, values in self.model.get_histograms().items():
            self.writer.histogram(name, values, step)

    def eval_all(self, step: int) -> dict[str, float]:
        if not self.datamanager.test_indices:
            return {}
        summary = evaluate_views(self.model, self.datamanager, progress=False)["summary"]
        self.writer.scalars({f"eval/{k}": v for k, v in summary.items() if v is not None}, step)
        return summary
