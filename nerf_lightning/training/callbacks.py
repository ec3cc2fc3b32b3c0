"""The run's own callbacks, which every ``nerf-train`` run has: the training clock, snapshots of validation renders
and the PSNR curve, checkpoints by steps or time, the run's config in every checkpoint, and a progress bar counted in
optimiser steps."""

from __future__ import annotations

import time
from datetime import timedelta
from pathlib import Path
from typing import Any

import imageio.v3 as iio
import lightning as L
import torch
from lightning.pytorch.callbacks import ModelCheckpoint
from lightning.pytorch.callbacks.progress.progress_bar import ProgressBar
from lightning.pytorch.loggers import TensorBoardLogger
from tqdm import tqdm

from nerf_lightning import __version__
from nerf_lightning.checkpoints import CHECKPOINT_FORMAT
from nerf_lightning.io import write_json, write_png
from nerf_lightning.outputs.plots import plot_psnr_curves
from nerf_lightning.outputs.video import write_gif

__all__ = ["RunConfigInCheckpoint", "Snapshots", "StepOrTimeCheckpoint", "StepProgressBar", "TimedCallback", "TrainingClock",
           "history_psnr"]


class TrainingClock:
    """Seconds of training: since :meth:`start`, less the stretches between :meth:`pause` and :meth:`resume`
    (validations), plus ``before`` (the seconds of earlier sessions of a resumed run)."""

    def __init__(self) -> None:
        self.before = 0.0
        self._started: float | None = None
        self._paused: float | None = None

    @property
    def running(self) -> bool:
        return self._started is not None

    def start(self) -> None:
        self._started = time.perf_counter()

    def pause(self) -> None:
        self._paused = time.perf_counter()

    def resume(self) -> None:
        if self._paused is not None and self._started is not None:
            self._started += time.perf_counter() - self._paused
        self._paused = None

    def seconds(self) -> float:
        if self._started is None:
            return self.before
        now = time.perf_counter()
        paused = now - self._paused if self._paused is not None else 0.0
        return self.before + now - self._started - paused


class TimedCallback(L.Callback):
    """A callback with a :class:`TrainingClock` that runs with training and stops during validations."""

    def __init__(self) -> None:
        self.clock = TrainingClock()

    def on_train_start(self, trainer: L.Trainer, pl_module: L.LightningModule) -> None:
        self.clock.start()

    def on_validation_start(self, trainer: L.Trainer, pl_module: L.LightningModule) -> None:
        self.clock.pause()

    def on_validation_end(self, trainer: L.Trainer, pl_module: L.LightningModule) -> None:
        self.clock.resume()


class Snapshots(TimedCallback):
    """Saves what each validation renders and the run's PSNR curve.

    Every image a validation step returns under ``images`` (name -> (H, W, 3) or (H, W) in [0, 1]) is
    written to ``<output_dir>/snapshots/<name>_<view>_step<step>.png`` and to TensorBoard as ``val/<name>_<view>``
    (the ``target`` images once only). The history of ``train/psnr`` (at the steps the logger writes) and ``val/psnr`` is
    written to ``psnr_history.json`` after each validation and plotted to ``psnr.png`` when training ends.
    The history is part of the callback's checkpoint state, so a resumed run keeps its whole curve.
    When training ends, the snapshots of the first view become ``montage.gif``: the fit over training.
    """

    def __init__(self, output_dir: str, dirname: str = "snapshots") -> None:
        self.output_dir = Path(output_dir)
        self.dirname = dirname
        self.history: dict[str, list[float]] = {
            "train_step": [], "train_psnr": [], "train_seconds": [], "val_step": [], "val_psnr": [], "val_seconds": []
        }
        self._targets_logged: set[int] = set()
        super().__init__()  # the clock: validation is not training time

    def on_train_batch_end(self, trainer: L.Trainer, pl_module: L.LightningModule, outputs: Any, batch: Any, batch_idx: int) -> None:
        # the PSNR the model logged from its photometric MSE, as TensorBoard shows it: not the total loss, which for
        # splats (L1 + D-SSIM) and the proposal presets (interlevel and distortion terms) is no MSE
        psnr = trainer.callback_metrics.get("train/psnr")
        if psnr is None or trainer.global_step % max(trainer.log_every_n_steps, 1) != 0:  # reading it waits on the device
            return
        self.history["train_step"].append(trainer.global_step)
        self.history["train_psnr"].append(float(psnr))
        self.history["train_seconds"].append(round(self.clock.seconds(), 4))

    def on_validation_batch_end(
        self, trainer: L.Trainer, pl_module: L.LightningModule, outputs: Any, batch: Any, batch_idx: int, dataloader_idx: int = 0
    ) -> None:
        if trainer.sanity_checking or not trainer.is_global_zero or not isinstance(outputs, dict):
            return
        step = trainer.global_step
        # Lightning logs this validation's scalars at step - 1 (the index of the batch just finished): match it
        tb_step = max(step - 1, 0)
        images = dict(outputs.get("images", {}))
        if "target" in images and "rgb" in images:
            # truth | render | depth, one picture to compare at a glance
            panels = [images["target"], images["rgb"]] + ([images["depth"][..., None].expand(-1, -1, 3)] if "depth" in images else [])
            side_by_side = torch.cat([panel.detach().float().cpu() for panel in panels], dim=1)
            for logger in trainer.loggers:
                if isinstance(logger, TensorBoardLogger):
                    logger.experiment.add_image(f"val/compare_{batch_idx:02d}", side_by_side.clamp(0, 1), tb_step, dataformats="HWC")
        for name, image in images.items():
            if name == "target":
                if batch_idx in self._targets_logged:
                    continue
                self._targets_logged.add(batch_idx)
            else:
                write_png(self.output_dir / self.dirname / f"{name}_{batch_idx:02d}_step{step:06d}.png", image)
            for logger in trainer.loggers:
                if isinstance(logger, TensorBoardLogger):
                    tb_image = image if image.ndim == 3 else image[..., None].expand(-1, -1, 3)
                    logger.experiment.add_image(f"val/{name}_{batch_idx:02d}", tb_image.clamp(0, 1).cpu(), tb_step, dataformats="HWC")

    def on_validation_epoch_end(self, trainer: L.Trainer, pl_module: L.LightningModule) -> None:
        if trainer.sanity_checking or "val/psnr" not in trainer.callback_metrics:
            return
        self.history["val_step"].append(trainer.global_step)
        self.history["val_psnr"].append(float(trainer.callback_metrics["val/psnr"]))
        # the validated weights are those after the last training step: its training clock, not the time since
        self.history["val_seconds"].append(self.history["train_seconds"][-1] if self.history["train_seconds"] else round(self.clock.seconds(), 4))
        if trainer.is_global_zero:
            write_json(self.output_dir / "psnr_history.json", self.history)

    def on_train_end(self, trainer: L.Trainer, pl_module: L.LightningModule) -> None:
        if not trainer.is_global_zero:
            return
        write_json(self.output_dir / "psnr_history.json", self.history)
        plot_psnr_curves(
            {
                "train (batch)": (self.history["train_step"], self.history["train_psnr"]),
                "val (whole image)": (self.history["val_step"], self.history["val_psnr"]),
            },
            self.output_dir / "psnr.png",
            title=f"PSNR over training: {self.output_dir.name}",
        )
        snapshots = sorted((self.output_dir / self.dirname).glob("rgb_00_step*.png"))
        if snapshots:
            write_gif(self.output_dir / "montage.gif", [iio.imread(path) for path in snapshots], fps=2.0)

    def state_dict(self) -> dict[str, Any]:
        return {"history": self.history, "training_seconds": self.clock.seconds()}

    def load_state_dict(self, state_dict: dict[str, Any]) -> None:
        self.history.update({key: list(values) for key, values in state_dict["history"].items()})
        self.clock.before = float(state_dict.get("training_seconds", 0.0))


class StepOrTimeCheckpoint(ModelCheckpoint):
    """Lightning's ModelCheckpoint saving every ``every_n_train_steps`` steps *or* every ``train_time_interval``
    seconds of training, whichever comes first (Lightning takes one or the other): a GPU makes many times a CPU's
    steps a second, so a time interval bounds the work a crash loses on both, and the step count keeps
    checkpoints at known steps where a test or a sweep needs them. Either may be None (off)."""

    def __init__(self, *args: Any, every_n_train_steps: int | None = None, train_time_interval: float | None = None, **kwargs: Any) -> None:
        super().__init__(*args, every_n_train_steps=every_n_train_steps, **kwargs)
        if train_time_interval is not None:
            if train_time_interval <= 0:
                raise ValueError(f"callbacks.last_checkpoint.train_time_interval must be a number of seconds > 0 or null, got {train_time_interval}")
            self._train_time_interval = timedelta(seconds=float(train_time_interval))


class RunConfigInCheckpoint(L.Callback):
    """Stores the run's resolved config and the model's kind in every checkpoint.

    ``nerf-render``, ``nerf-eval`` and ``nerf-export`` rebuild the model from this config, so a checkpoint
    is all they need.
    """

    def __init__(self, config: dict[str, Any]) -> None:
        self.config = config

    def on_save_checkpoint(self, trainer: L.Trainer, pl_module: L.LightningModule, checkpoint: dict[str, Any]) -> None:
        checkpoint["nerf_lightning"] = {
            "kind": getattr(pl_module, "kind", type(pl_module).__name__), "config": self.config, "format": CHECKPOINT_FORMAT, "version": __version__,
        }


class StepProgressBar(ProgressBar):
    """One bar over the run's optimiser steps, with steps a second, the current training PSNR and the last
    validation PSNR (Lightning's own bar counts "epochs", which here are the stretches between validations).
    ``nerf-train`` uses it wherever ``trainer.enable_progress_bar`` is true."""

    def __init__(self) -> None:
        super().__init__()
        self._enabled = True
        self.bar: tqdm | None = None

    def disable(self) -> None:
        self._enabled = False

    def enable(self) -> None:
        self._enabled = True

    @property
    def is_enabled(self) -> bool:
        return self._enabled

    def on_train_start(self, trainer: L.Trainer, pl_module: L.LightningModule) -> None:
        if self.is_enabled and trainer.is_global_zero:
            total = trainer.max_steps if trainer.max_steps and trainer.max_steps > 0 else None
            self.bar = tqdm(total=total, initial=trainer.global_step, unit="step", desc="training", dynamic_ncols=True, smoothing=0.05)

    def on_train_batch_end(self, trainer: L.Trainer, pl_module: L.LightningModule, outputs: Any, batch: Any, batch_idx: int) -> None:
        if self.bar is None:
            return
        self.bar.update(trainer.global_step - self.bar.n)
        if trainer.global_step % max(trainer.log_every_n_steps, 1) == 0:  # reading the metrics waits on the device
            self._show_psnr(trainer, refresh=False)

    def _show_psnr(self, trainer: L.Trainer, refresh: bool) -> None:
        # the logged tensors, read here and only here: a metric logged with prog_bar=True would be read back by
        # Lightning after every step (a wait for the device each step)
        shown = {key.replace("/", " "): f"{float(value):.2f}" for key, value in trainer.callback_metrics.items()
                 if key in ("train/psnr", "val/psnr")}
        self.bar.set_postfix(shown, refresh=refresh)

    def on_validation_start(self, trainer: L.Trainer, pl_module: L.LightningModule) -> None:
        if self.bar is not None:
            self.bar.set_description_str("validating", refresh=True)

    def on_validation_end(self, trainer: L.Trainer, pl_module: L.LightningModule) -> None:
        if self.bar is not None:
            self.bar.set_description_str("training", refresh=False)
            self._show_psnr(trainer, refresh=True)  # the new validation PSNR (validation has waited for the device already)

    def _close(self) -> None:
        if self.bar is not None:
            self.bar.close()
            self.bar = None

    def on_train_end(self, trainer: L.Trainer, pl_module: L.LightningModule) -> None:
        self._close()

    def on_exception(self, trainer: L.Trainer, pl_module: L.LightningModule, exception: BaseException) -> None:
        self._close()


def history_psnr(history: dict[str, list[float]]) -> tuple[list[float], list[float]]:
    """The validation curve of a ``psnr_history.json``, falling back to the training curve."""
    if history.get("val_step"):
        return history["val_step"], history["val_psnr"]
    return history.get("train_step", []), history.get("train_psnr", [])
