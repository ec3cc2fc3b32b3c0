"""Lightning callbacks: snapshots of validation renders, PSNR history and curve, the run's config in checkpoints."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import lightning as L
from lightning.pytorch.loggers import TensorBoardLogger

from nerf_lightning.io import write_json, write_png
from nerf_lightning.metrics import mse_to_psnr
from nerf_lightning.plots import plot_psnr_curves


class Snapshots(L.Callback):
    """Saves what each validation renders and the run's PSNR curve.

    Every image a validation step returns under ``images`` (name -> (H, W, 3) or (H, W) in [0, 1]) is
    written to ``<output_dir>/snapshots/<name>_<view>_step<step>.png`` and to TensorBoard as ``val/<name>_<view>``
    (the ``target`` images once only). The history of ``train/psnr`` (every step) and ``val/psnr`` is
    written to ``psnr_history.json`` after each validation and plotted to ``psnr.png`` when training ends.
    The history is part of the callback's checkpoint state, so a resumed run keeps its whole curve.
    """

    def __init__(self, output_dir: str, dirname: str = "snapshots") -> None:
        self.output_dir = Path(output_dir)
        self.dirname = dirname
        self.history: dict[str, list[float]] = {"train_step": [], "train_psnr": [], "val_step": [], "val_psnr": []}
        self._targets_logged: set[int] = set()

    def on_train_batch_end(self, trainer: L.Trainer, pl_module: L.LightningModule, outputs: Any, batch: Any, batch_idx: int) -> None:
        loss = outputs["loss"] if isinstance(outputs, dict) else outputs
        if loss is None:
            return
        self.history["train_step"].append(trainer.global_step)
        self.history["train_psnr"].append(float(mse_to_psnr(loss.detach().float())))

    def on_validation_batch_end(
        self, trainer: L.Trainer, pl_module: L.LightningModule, outputs: Any, batch: Any, batch_idx: int, dataloader_idx: int = 0
    ) -> None:
        if trainer.sanity_checking or not trainer.is_global_zero or not isinstance(outputs, dict):
            return
        step = trainer.global_step
        # Lightning logs this validation's scalars at step - 1 (the index of the batch just finished): match it
        tb_step = max(step - 1, 0)
        for name, image in outputs.get("images", {}).items():
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

    def state_dict(self) -> dict[str, Any]:
        return {"history": self.history}

    def load_state_dict(self, state_dict: dict[str, Any]) -> None:
        self.history = {key: list(values) for key, values in state_dict["history"].items()}


class RunConfigInCheckpoint(L.Callback):
    """Stores the run's resolved config and the model's kind in every checkpoint.

    ``nerf-render``, ``nerf-eval`` and ``nerf-export`` rebuild the model from this config, so a checkpoint
    is all they need.
    """

    def __init__(self, config: dict[str, Any]) -> None:
        self.config = config

    def on_save_checkpoint(self, trainer: L.Trainer, pl_module: L.LightningModule, checkpoint: dict[str, Any]) -> None:
        checkpoint["nerf_lightning"] = {"kind": getattr(pl_module, "kind", type(pl_module).__name__), "config": self.config}


def history_psnr(history: dict[str, list[float]]) -> tuple[list[float], list[float]]:
    """The validation curve of a ``psnr_history.json``, falling back to the training curve."""
    if history.get("val_step"):
        return history["val_step"], history["val_psnr"]
    return history.get("train_step", []), history.get("train_psnr", [])


__all__ = ["RunConfigInCheckpoint", "Snapshots", "history_psnr"]
