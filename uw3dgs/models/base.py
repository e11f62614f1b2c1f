"""The interface every method's model implements; the Trainer knows nothing else about a method."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

from torch import Tensor, nn

from uw3dgs.cameras import Camera
from uw3dgs.config import InstantiateConfig, Target, target
from uw3dgs.data.datamanager import Batch
from uw3dgs.data.scene import SceneData, scene_extent
from uw3dgs.engine.callbacks import TrainingCallback
from uw3dgs.engine.optimizers import Optimizers
from uw3dgs.kernels.policy import Kernels
from uw3dgs.medium.formation import Water
from uw3dgs.metrics.image import psnr, ssim
from uw3dgs.metrics.lpips import lpips_metrics
from uw3dgs.metrics.underwater_quality import underwater_quality


@dataclass(frozen=True)
class ModelConfig(InstantiateConfig):
    _target: Target = target(lambda: Model)
    kernels: Kernels = "compiled"
    """The compiled CPU kernels or their PyTorch references for every part of the model that has both (colours, the
    medium's and the radiance field's VM reads, SSIM of the loss, the method's own losses and passes): 'compiled' =
    compiled where the tensors are CPU float32/float64 and the module builds, PyTorch elsewhere (CUDA); 'torch' =
    PyTorch everywhere (the reference; the same numbers to float rounding). The rasterizer is chosen by
    --model.raster.backend."""


class Model(nn.Module):
    """A scene representation plus how it renders, what it is trained with and what it reports.

    Built as `config.setup(scene=..., train_indices=...)`: the model sees the loaded scene (initial
    points, cameras, bounds) but not the datamanager.
    """

    def __init__(self, config: ModelConfig, scene: SceneData, train_indices: list[int]):
        super().__init__()
        self.config = config
        self.train_indices = list(train_indices)
        """The scene's views the model trains on (whole-model evaluation numbers are measured over them)."""
        self.scene_extent = scene_extent([scene.cameras[i] for i in train_indices])

    def param_groups(self) -> dict[str, list[nn.Parameter]]:
        """Named parameter groups; the method's optimizer configs give each its learning rate."""
        raise NotImplementedError

    def get_outputs(self, camera: Camera) -> dict[str, Any]:
        """Render one view. Must contain 'rgb' [H, W, 3], the image compared with the dataset's."""
        raise NotImplementedError

    def rays_per_batch(self) -> int | None:
        """None (the default): each training step gets one view (`DataManager.next_train`); a number: that many random
        rays across the training views (`DataManager.next_train_rays`, ray-marching methods)."""
        return None

    def get_train_outputs(self, batch: Batch) -> dict[str, Any]:
        """What a training step renders for `batch`. Default: `get_outputs` of the batch's view."""
        return self.get_outputs(batch["camera"])

    def get_loss_dict(self, outputs: dict[str, Any], batch: Batch, step: int) -> dict[str, Tensor]:
        """Weighted loss terms; the Trainer back-propagates their sum."""
        raise NotImplementedError

    def get_metrics_dict(self, outputs: dict[str, Any], batch: Batch) -> dict[str, float]:
        """Scalars for the progress bar and TensorBoard."""
        return {}

    def get_eval_metrics(self, outputs: dict[str, Any], batch: Batch) -> dict[str, float | None]:
        """Per-test-view metrics for evaluation: PSNR, SSIM and LPIPS (alex, vgg) of 'rgb' against the dataset's
        image; the no-reference UCIQE and UIQM of 'rgb' (`uciqe`, `uiqm`), of the dataset's image (`input_uciqe`,
        `input_uiqm`) and of its clean image where it has one (`clean_uciqe`, `clean_uiqm`); and the PSNR over the
        pixels training views see where the dataset tells them ('covisible'). A metric a view cannot give is None
        (reported missing; means are over the views that have it), e.g. LPIPS without its weights installed."""
        pred = outputs["rgb"].detach().clamp(0, 1)
        metrics: dict[str, float | None] = {"psnr": float(psnr(pred, batch["image"])),
                                            "ssim": float(ssim(pred, batch["image"]))}
        metrics.update(lpips_metrics(pred, batch["image"]))
        metrics.update(underwater_quality(pred))
        metrics.update(underwater_quality(batch["image"], prefix="input_"))
        if "clean_image" in batch:
            metrics.update(underwater_quality(batch["clean_image"], prefix="clean_"))
        if "covisible" in batch:
            metrics["psnr_covisible"] = float(psnr(pred, batch["image"], batch["covisible"]))
            metrics["covisible_share"] = float(batch["covisible"].float().mean())
        return metrics

    def get_eval_summary(self, scene: SceneData) -> dict[str, float | None]:
        """Whole-model numbers for evaluation (not per view), e.g. the learned medium against ground truth; None
        where the model cannot give one (reported missing). Called by evaluation outside eval mode: a summary that
        renders switches to eval mode itself."""
        return {}

    def get_image_dict(self, outputs: dict[str, Any], batch: Batch) -> dict[str, Tensor]:
        """Named [H, W, 3] images in [0, 1] for TensorBoard and the saved renders."""
        return {}

    def get_histograms(self) -> dict[str, Tensor]:
        """Named per-Gaussian values for TensorBoard histograms (logged with the eval image). Default: none."""
        return {}

    def get_training_callbacks(self, optimizers: Optimizers, max_num_iterations: int) -> list[TrainingCallback]:
        """Hooks into the training loop (schedules, density control); their state is checkpointed."""
        return []

    def initialize_from_data(self, scene: SceneData, train_indices: list[int]) -> None:
        """Called by the Trainer once on a fresh run, after the model is on its device and before step 1 (never
        on `--resume` or when a trained model is loaded for evaluation): fits that need the training views and
        whose result a checkpoint holds anyway, e.g. a starting medium. Default: nothing."""

    def run_notes(self) -> dict[str, dict]:
        """JSON documents (name -> content) about how this run started, which the Trainer writes into the run folder
        (`notes/NAME.json`) after `initialize_from_data` and uw-eval copies into its JSON ('notes'). Default:
        none."""
        return {}

    # What the viewing and export commands ask of a model (uw-render, uw-viewer, uw-export): no command looks at a
    # model's class or its fields.

    def render_view(self, camera: Camera, water: Water | None = None) -> dict[str, Tensor]:
        """One view as the viewer and uw-render show it, called under no_grad, possibly from another thread while
        training: it must change no state (no train/eval switch, no random numbers drawn). 'rgb' [H, W, 3] the
        rendered image (for a method with water, the underwater image), 'alpha' [H, W], 'range' [H, W] (world units;
        the far bound where nothing covers a pixel); and where the method has them 'uri' (the water-free image),
        'attenuation', 'backscatter' [H, W, 3]. `water`: the water control (`veiling_light` not None), None = as
        learned. Default: `get_outputs` (a model whose outputs depend on its mode overrides this)."""
        return self.get_outputs(camera)

    def veiling_light(self) -> Tensor | None:
        """The learned B_inf [3] where the model forms its image through `uw3dgs.medium.formation` (the viewer then
        offers its water control and `render_view` takes a `Water`); None without one. Default: None."""
        return None

    def export_medium(self, dataset_center: tuple[float, float, float], dataset_scale: float,
                      samples: int) -> dict | None:
        """The learned medium as `uw-export` writes it (`uw3dgs.medium.field.Medium.summary`, in the dataset frame;
        `samples` points per axis for one that varies in space); None for a method without one. Default: None."""
        return None

    def eval_report(self, notes: dict[str, dict]) -> dict[str, Any]:
        """Entries `uw-eval` adds to its JSON (and may print), given the run's notes (`run_notes`), e.g. a judgement
        made before training made again on the trained model. Default: none."""
        return {}

    def state_keys_resized_in_training(self) -> set[str]:
        """state_dict keys whose first dimension changes during training (density control changes the number of
        Gaussians); `--resume` compares every other shape with the checkpoint's exactly. Default: none."""
        return set()

    def checkpoint_defaults(self) -> dict[str, Tensor]:
        """state_dict entries a checkpoint written before they existed lacks, with the value that means what such a
        run did (`--resume` and `uw-eval` then take it). Default: none."""
        return {}

    def state_keys_reshaped_in_training(self) -> set[str]:
        """state_dict keys whose whole shape (not their number of dimensions) changes during training (a grid that
        grows); `--resume` leaves their shapes to `load_checkpoint_state`. Default: none."""
        return set()

    def load_checkpoint_state(self, state: dict[str, Tensor]) -> None:
        """Load weights saved by `state_dict()` (override when parameter shapes change in training); entries of
        `checkpoint_defaults` the checkpoint lacks take their default."""
        self.load_state_dict({**self.checkpoint_defaults(), **state})
