"""What every model here shares: an optimiser over named parameter groups and an optional per-step scheduler, both
built from Hydra partials; parameters replaced or resized with their optimiser state; a stop on a non-finite loss;
the random state in checkpoints, so a resumed run draws what the uninterrupted one would."""

from __future__ import annotations

import math
from collections.abc import Callable
from typing import Any

import lightning as L
import torch
from torch import nn

from torchmetrics import MeanMetric

from nerf_lightning.data.batches import HeldOutView
from nerf_lightning.errors import NonFiniteLossError
from nerf_lightning.geometry.space import SceneSpace
from nerf_lightning.metrics import image_metrics
from nerf_lightning.parameters.groups import GroupSchedules, check_groups, replace_parameter, resize_to_saved


def depth_for_depth_loss(batch: dict[str, Any], key: str = "model.depth_loss") -> torch.Tensor:
    """The batch's ``depth`` (a capture's depth maps), or one line saying what the depth loss (``key``) needs."""
    if "depth" not in batch:
        raise ValueError(f"{key} > 0 needs depth in each training batch: a capture whose frames have a 'depth_file_path' "
                         f"(data/scene=transforms) or the procedural scene; set {key}=0 otherwise")
    return batch["depth"]


def masks_for_mask_loss(batch: dict[str, Any]) -> torch.Tensor:
    """The batch's ``object_mask``, or one line saying what ``model.mask_loss`` needs."""
    if "object_mask" not in batch:
        raise ValueError("model.mask_loss > 0 needs the object's masks in each training batch: data.masks=background "
                         "(and a capture with masks); set model.mask_loss=0 otherwise")
    return batch["object_mask"]


class FieldModule(L.LightningModule):
    """A LightningModule that builds its optimiser and learning-rate scheduler from factories.

    The optimiser trains the groups of :meth:`parameter_groups`, each at its own learning rate and schedule if it
    has them (:mod:`~nerf_lightning.parameters.groups`). :meth:`replace_parameter` swaps a parameter for one of
    another size, its optimiser state carried row by row; the parameters a model names in
    ``variable_size_parameters`` load from a checkpoint at the size they were saved with.

    A NaN or infinite training loss stops the run with :class:`~nerf_lightning.errors.NonFiniteLossError` before
    it reaches the weights (checked every step on a CPU, where it costs nothing; on a GPU every
    ``trainer.log_every_n_steps`` steps, so that the step does not wait on the device, and the checkpoint writer
    refuses non-finite weights in between); the checkpoints keep the last finite weights. Checkpoints carry torch's random state
    (CPU and CUDA), restored on resuming, so that stratified jitter continues as in an uninterrupted run.

    Args:
        optimizer: builds the optimiser from the parameter groups (a Hydra ``_partial_``).
        scheduler: builds a scheduler stepped every optimiser step from the optimiser, for the groups without a
            schedule of their own; or None.
    """

    kind = "field"

    def __init__(self, optimizer: Callable[..., torch.optim.Optimizer], scheduler: Callable[..., Any] | None = None) -> None:
        super().__init__()
        self.make_optimizer = optimizer
        self.make_scheduler = scheduler

    def parameter_groups(self) -> list[dict[str, Any]]:
        """What the optimiser trains: named groups, ``{"name": str, "params": [...], "lr": float (optional: else the
        optimiser's), "schedule": step -> factor of that lr (optional: else the configured scheduler's)}`` and any
        other option of torch's groups; every trainable parameter in one group
        (:func:`~nerf_lightning.parameters.groups.check_groups`). Here: one group, ``model``, of every parameter."""
        return [{"name": "model", "params": list(self.parameters())}]

    def configure_optimizers(self) -> Any:
        groups = check_groups(self.parameter_groups(), self)
        options = [{key: value for key, value in group.items() if key != "schedule"} for group in groups]
        if len(options) == 1:  # LearningRateMonitor then logs lr-Adam, as before groups had names, not lr-Adam/model
            del options[0]["name"]
        optimizer = self.make_optimizer(params=options)
        scheduler = None if self.make_scheduler is None else self.make_scheduler(optimizer=optimizer)
        schedules = [group.get("schedule") for group in groups]
        if any(schedule is not None for schedule in schedules):
            scheduler = GroupSchedules(optimizer, schedules, fallback=scheduler)
        if scheduler is None:
            return optimizer
        return {"optimizer": optimizer, "lr_scheduler": {"scheduler": scheduler, "interval": "step"}}

    def replace_parameter(self, owner: nn.Module, name: str, value: torch.Tensor, rows_from: torch.Tensor | None = None) -> nn.Parameter:
        """Set ``owner.<name>`` to a new parameter holding ``value`` (any size), in the old one's place in the
        optimiser if it is built, its state (Adam's moments) taken row by row as ``rows_from`` (N_new,) says: the old
        row for each new row, or -1 for zeros. See :func:`~nerf_lightning.parameters.groups.replace_parameter`."""
        optimizers = self._trainer.optimizers if self._trainer is not None else []
        return replace_parameter(owner, name, value, optimizers, rows_from)

    def logs_this_step(self) -> bool:
        """Whether the logger writes this training step's values (global_step counts the steps before this one; the
        logger, the progress bar and the PSNR history look after the optimiser step, one higher): what only they read
        need be made only then."""
        trainer = self._trainer
        if trainer is None:
            return True
        step = self.global_step + 1
        return step % max(trainer.log_every_n_steps, 1) == 0 or (trainer.max_steps is not None and step >= trainer.max_steps > 0)

    def on_before_backward(self, loss: torch.Tensor) -> None:
        # on a GPU only at the steps that log, which read values back anyway
        if self.device.type != "cpu" and not self.logs_this_step():
            return
        if not math.isfinite(loss.detach().item()):  # one read of the value, not the four operators of isfinite
            raise NonFiniteLossError(
                f"step {self.global_step}: the training loss is {float(loss.detach())}; the run stops here and its last checkpoint keeps "
                "the last finite weights. A lower model.optimizer.lr usually helps: start a new run with it (resuming restores "
                "the optimiser with its old learning rate)"
            )

    def on_save_checkpoint(self, checkpoint: dict[str, Any]) -> None:
        checkpoint["rng_state"] = {"torch": torch.get_rng_state(), "cuda": torch.cuda.get_rng_state_all() if torch.cuda.is_available() else []}

    def on_load_checkpoint(self, checkpoint: dict[str, Any]) -> None:
        """Size the variable-size parameters as saved (Lightning calls this before ``load_state_dict`` and before
        it builds the optimiser; so does :func:`~nerf_lightning.checkpoints.load_model`), and restore the random state."""
        resize_to_saved(self, checkpoint.get("state_dict", {}), replace=self.replace_parameter)
        state = checkpoint.get("rng_state")
        if state:
            torch.set_rng_state(state["torch"])
            if state["cuda"] and torch.cuda.is_available() and len(state["cuda"]) == torch.cuda.device_count():
                torch.cuda.set_rng_state_all(state["cuda"])


class SceneModule(FieldModule):
    """A model of a posed scene (a radiance field, Gaussian splats): it renders cameras (``render_view``, the model
    contract) in the scene's space (:class:`~nerf_lightning.geometry.space.SceneSpace`, kept in checkpoints), and
    validates on whole held-out views: ``val/psnr``, ``val/ssim``, with masks ``val/psnr_masked``
    (:mod:`~nerf_lightning.data.masks`) and, where the scene has true depth, ``val/depth_error`` (:func:`~nerf_lightning.metrics.image_metrics`), the renders returned for the snapshots."""

    def __init__(self, optimizer: Callable[..., torch.optim.Optimizer], scheduler: Callable[..., Any] | None = None) -> None:
        super().__init__(optimizer, scheduler)
        self.space = SceneSpace()
        # the mean over the validated views where a surface is seen (NaN views left out), summed over DDP ranks
        self.val_depth_error = MeanMetric(nan_strategy="ignore")

    def validation_step(self, batch: HeldOutView, batch_idx: int) -> dict[str, Any]:
        height, width = batch["height"], batch["width"]
        out = self.render_view(batch["K"], batch["c2w"], height, width)
        target, true_depth, mask = batch["image"], batch.get("depth"), batch.get("object_mask")
        metrics = image_metrics(out["rgb"], target, out["depth"], true_depth, mask)
        self.log("val/psnr", metrics["psnr"], prog_bar=True, batch_size=1, sync_dist=True)
        self.log("val/ssim", metrics["ssim"], batch_size=1, sync_dist=True)
        if mask is not None:  # a capture with masks: the object alone, besides the whole image
            self.log("val/psnr_masked", metrics["psnr_masked"], batch_size=1, sync_dist=True)
        if "depth_error" in metrics:  # every rank validates views of the same scene: all log the key, or none does
            self.val_depth_error.update(metrics["depth_error"])
            self.log("val/depth_error", self.val_depth_error, batch_size=1)
        picture = self.space.depth_picture(out["depth"], out["accumulation"])
        return {"images": {"rgb": out["rgb"], "depth": picture, "target": target}}

    def on_save_checkpoint(self, checkpoint: dict[str, Any]) -> None:
        super().on_save_checkpoint(checkpoint)
        checkpoint["scene_space"] = self.space.state()

    def on_load_checkpoint(self, checkpoint: dict[str, Any]) -> None:
        super().on_load_checkpoint(checkpoint)
        if checkpoint.get("scene_space"):
            self.space = SceneSpace.from_state(checkpoint["scene_space"]).to(self.device)
