"""The benchmark runner's callbacks: training stopped after a budget of training minutes, and checkpoints kept at
minute marks for the PSNR-against-minutes curves. Validation time is not counted by either (the training clock of
:class:`~nerf_lightning.training.callbacks.TimedCallback`), so every preset gets the same training time however long it
validates."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import lightning as L

from nerf_lightning.training.callbacks import TimedCallback
from nerf_lightning.devices import synchronize
from nerf_lightning.io import write_json


class CheckpointAtMinutes(TimedCallback):
    """Saves ``<dirpath>/minute_<m>.ckpt`` when training time first reaches each of ``minutes`` (validation not
    counted), and the last weights as the remaining marks' when training stops before them; ``marks.json`` there
    lists each file's step and training seconds. For PSNR-against-time curves measured after training
    (``nerf-bench``), so that evaluating costs the run nothing."""

    def __init__(self, dirpath: str, minutes: list[float]) -> None:
        if not minutes or any(m <= 0 for m in minutes):
            raise ValueError(f"CheckpointAtMinutes.minutes must be a list of minutes > 0, got {minutes}")
        self.dirpath = Path(dirpath)
        self.pending = sorted(float(m) for m in minutes)
        self.marks: list[dict[str, Any]] = []
        super().__init__()

    def _save(self, trainer: L.Trainer, minutes: float, seconds: float) -> None:
        path = self.dirpath / f"minute_{minutes:g}.ckpt"
        trainer.save_checkpoint(path)
        self.marks.append({"minutes": minutes, "path": str(path), "step": trainer.global_step, "training_seconds": round(seconds, 2)})
        if trainer.is_global_zero:
            write_json(self.dirpath / "marks.json", self.marks)

    def on_train_batch_end(self, trainer: L.Trainer, pl_module: L.LightningModule, outputs: Any, batch: Any, batch_idx: int) -> None:
        if not self.pending or not self.clock.running:
            return
        seconds = self.clock.seconds()
        if seconds >= self.pending[0] * 60:
            synchronize(pl_module.device)  # the clock counts the queued steps too
            seconds = self.clock.seconds()
            self._save(trainer, self.pending.pop(0), seconds)

    def on_train_end(self, trainer: L.Trainer, pl_module: L.LightningModule) -> None:
        if self.pending and self.clock.running:
            seconds = self.clock.seconds()
            for minutes in list(self.pending):  # max_time or max_steps came first: the last weights stand for the rest
                self._save(trainer, minutes, seconds)
            self.pending.clear()


class StopAtTrainingMinutes(TimedCallback):
    """Stops training once training time reaches ``minutes`` (validation not counted, unlike ``trainer.max_time``),
    so that a benchmark gives every method the same training time however long its validations take."""

    def __init__(self, minutes: float) -> None:
        if minutes <= 0:
            raise ValueError(f"StopAtTrainingMinutes.minutes must be > 0, got {minutes}")
        self.minutes = float(minutes)
        super().__init__()

    def on_train_batch_end(self, trainer: L.Trainer, pl_module: L.LightningModule, outputs: Any, batch: Any, batch_idx: int) -> None:
        if self.clock.running and self.clock.seconds() >= self.minutes * 60:
            synchronize(pl_module.device)
            trainer.should_stop = True
