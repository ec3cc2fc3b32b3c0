"""What every model here shares: an optimiser and an optional per-step scheduler, both built from Hydra partials; a
stop on a non-finite loss; the random state in checkpoints, so a resumed run draws what the uninterrupted one would."""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import lightning as L
import torch

from nerf_lightning.errors import NonFiniteLossError


class FieldModule(L.LightningModule):
    """A LightningModule that builds its optimiser and learning-rate scheduler from factories.

    A NaN or infinite training loss stops the run with :class:`~nerf_lightning.errors.NonFiniteLossError` before
    it reaches the weights (checked every step on a CPU, where it costs nothing; on a GPU every
    ``trainer.log_every_n_steps`` steps, so that the step does not wait on the device, and the checkpoint writer
    refuses non-finite weights in between); the checkpoints keep the last finite weights. Checkpoints carry torch's random state
    (CPU and CUDA), restored on resuming, so that stratified jitter continues as in an uninterrupted run.

    Args:
        optimizer: builds the optimiser from the parameters (a Hydra ``_partial_``).
        scheduler: builds a scheduler stepped every optimiser step from the optimiser; or None.
    """

    kind = "field"

    def __init__(self, optimizer: Callable[..., torch.optim.Optimizer], scheduler: Callable[..., Any] | None = None) -> None:
        super().__init__()
        self.make_optimizer = optimizer
        self.make_scheduler = scheduler

    def parameter_groups(self) -> Any:
        """What the optimiser trains: every parameter, or a list of groups (dicts with their own options)."""
        return self.parameters()

    def configure_optimizers(self) -> Any:
        optimizer = self.make_optimizer(params=self.parameter_groups())
        if self.make_scheduler is None:
            return optimizer
        return {"optimizer": optimizer, "lr_scheduler": {"scheduler": self.make_scheduler(optimizer=optimizer), "interval": "step"}}

    def on_before_backward(self, loss: torch.Tensor) -> None:
        if self.device.type != "cpu" and self.global_step % max(self.trainer.log_every_n_steps, 1) != 0:
            return
        if not bool(torch.isfinite(loss.detach())):
            raise NonFiniteLossError(
                f"step {self.global_step}: the training loss is {float(loss.detach())}; the run stops here and its last checkpoint keeps "
                "the last finite weights. A lower model.optimizer.lr usually helps: start a new run with it (resuming restores "
                "the optimiser with its old learning rate)"
            )

    def on_save_checkpoint(self, checkpoint: dict[str, Any]) -> None:
        checkpoint["rng_state"] = {"torch": torch.get_rng_state(), "cuda": torch.cuda.get_rng_state_all() if torch.cuda.is_available() else []}

    def on_load_checkpoint(self, checkpoint: dict[str, Any]) -> None:
        state = checkpoint.get("rng_state")
        if state:
            torch.set_rng_state(state["torch"])
            if state["cuda"] and torch.cuda.is_available() and len(state["cuda"]) == torch.cuda.device_count():
                torch.cuda.set_rng_state_all(state["cuda"])
