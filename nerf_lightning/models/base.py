"""What every model here shares: an optimiser and an optional per-step scheduler, both built from Hydra partials."""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import lightning as L
import torch


class FieldModule(L.LightningModule):
    """A LightningModule that builds its optimiser and learning-rate scheduler from factories.

    Args:
        optimizer: builds the optimiser from the parameters (a Hydra ``_partial_``).
        scheduler: builds a scheduler stepped every optimiser step from the optimiser; or None.
    """

    kind = "field"

    def __init__(self, optimizer: Callable[..., torch.optim.Optimizer], scheduler: Callable[..., Any] | None = None) -> None:
        super().__init__()
        self.make_optimizer = optimizer
        self.make_scheduler = scheduler

    def configure_optimizers(self) -> Any:
        optimizer = self.make_optimizer(params=self.parameters())
        if self.make_scheduler is None:
            return optimizer
        return {"optimizer": optimizer, "lr_scheduler": {"scheduler": self.make_scheduler(optimizer=optimizer), "interval": "step"}}
