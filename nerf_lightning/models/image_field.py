"""Fitting a neural field to one image."""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import kornia
import torch
import torch.nn.functional as F
from torch import nn

from nerf_lightning.data.images import pixel_grid
from nerf_lightning.metrics import mse_to_psnr
from nerf_lightning.models.base import FieldModule


class ImageFieldModule(FieldModule):
    """Trains an image field (positions (N, 2) -> colours (N, 3)) with an MSE loss on random pixels.

    Logs ``train/loss`` and ``train/psnr`` every step and ``val/psnr`` of the whole image at each validation.
    Its validation step returns the rendered image under ``images`` for the snapshot callback.

    Args:
        field: the image field, for example :class:`~nerf_lightning.fields.ImageField`.
        optimizer, scheduler: see :class:`~nerf_lightning.models.base.FieldModule`.
        chunk_size: pixels evaluated at once when rendering, so memory stays bounded at any resolution.
    """

    kind = "image_field"

    def __init__(
        self,
        field: nn.Module,
        optimizer: Callable[..., torch.optim.Optimizer],
        scheduler: Callable[..., Any] | None = None,
        chunk_size: int = 65_536,
    ) -> None:
        super().__init__(optimizer, scheduler)
        self.field = field
        self.chunk_size = chunk_size
        self.image_size: tuple[int, int] | None = None  # (H, W) of the fitted image, kept in checkpoints

    def forward(self, xy: torch.Tensor) -> torch.Tensor:
        """(..., 2) positions in [0, 1] -> (..., 3) colours."""
        return self.field(xy)

    def on_fit_start(self) -> None:
        datamodule = getattr(self.trainer, "datamodule", None)
        if datamodule is not None and hasattr(datamodule, "image_size"):
            self.image_size = datamodule.image_size

    def training_step(self, batch: dict[str, torch.Tensor], batch_idx: int) -> torch.Tensor:
        rgb = self.field(batch["xy"])
        loss = F.mse_loss(rgb, batch["rgb"])
        self.log("train/loss", loss, on_step=True, on_epoch=False)
        self.log("train/psnr", mse_to_psnr(loss.detach()), on_step=True, on_epoch=False)
        return loss

    @torch.no_grad()
    def render(self, xy: torch.Tensor) -> torch.Tensor:
        """(..., 2) positions -> (..., 3) colours, evaluated ``chunk_size`` at a time."""
        flat = xy.reshape(-1, 2)
        rgb = torch.cat([self.field(chunk) for chunk in flat.split(self.chunk_size)])
        return rgb.reshape(*xy.shape[:-1], 3)

    def render_image(self, scale: float = 1.0) -> torch.Tensor:
        """The fitted image rendered ``scale`` times its size: (round(sH), round(sW), 3)."""
        if self.image_size is None:
            raise RuntimeError("this image field has no image size: it was not trained through Lightning's fit")
        height, width = self.image_size
        return self.render(pixel_grid(height, width, scale).to(self.device))

    def validation_step(self, batch: dict[str, Any], batch_idx: int) -> dict[str, Any]:
        height, width = batch["height"], batch["width"]
        rgb = self.render(batch["xy"]).reshape(height, width, 3)
        target = batch["image"]
        psnr = kornia.metrics.psnr(rgb, target, max_val=1.0)
        self.log("val/psnr", psnr, prog_bar=True, batch_size=1, sync_dist=True)
        return {"images": {"rgb": rgb, "target": target}}

    def on_save_checkpoint(self, checkpoint: dict[str, Any]) -> None:
        super().on_save_checkpoint(checkpoint)
        checkpoint["image_size"] = self.image_size

    def on_load_checkpoint(self, checkpoint: dict[str, Any]) -> None:
        super().on_load_checkpoint(checkpoint)
        self.image_size = tuple(checkpoint["image_size"]) if checkpoint.get("image_size") else None
