"""Batches of random pixels of one image, for fitting an image field."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import torch
from torch.utils.data import DataLoader

from nerf_lightning.data.batches import StepBatchesDataModule
from nerf_lightning.data.images import default_image, downscale, load_image, pixel_grid


class PixelDataModule(StepBatchesDataModule):
    """Each training step a batch of ``batch_size`` random pixels of one image; validation sees it whole.

    Training batch: ``xy`` (N, 2) pixel-centre positions, x divided by the width and y by the height, in
    [0, 1]; ``rgb`` (N, 3) colours in [0, 1] (8-bit values / 255). Pixels are drawn uniformly with
    replacement. Validation batch: every pixel's ``xy`` (H*W, 2) in row-major order, the ``image`` (H, W, 3), and
    ``height`` and ``width``.

    Args:
        path: a PNG or JPG; None uses the built-in :func:`default_image`.
        batch_size: pixels per training step.
        downscale: integer factor, area averaging.
        val_steps, val_every, seed: see :class:`~nerf_lightning.data.batches.StepBatchesDataModule`.
    """

    def __init__(
        self,
        path: str | None = None,
        batch_size: int = 10_000,
        downscale: int = 1,
        val_steps: list[int] | tuple[int, ...] = (10, 100, 200, 400, 1000),
        val_every: int | None = None,
        seed: int = 0,
    ) -> None:
        super().__init__(batch_size=batch_size, val_steps=val_steps, val_every=val_every, seed=seed)
        self.path = path
        self.downscale_factor = downscale
        self.image: torch.Tensor | None = None  # (H, W, 3)

    def setup(self, stage: str | None = None) -> None:
        if self.image is not None:
            return
        image = default_image() if self.path is None else load_image(Path(self.path).expanduser())
        self.image = downscale(image, self.downscale_factor)
        height, width = self.image.shape[:2]
        self.xy = pixel_grid(height, width).reshape(-1, 2)  # (H*W, 2)
        self.rgb = self.image.reshape(-1, 3)  # (H*W, 3)

    @property
    def image_size(self) -> tuple[int, int]:
        """(height, width) of the fitted image."""
        assert self.image is not None, "call setup() first"
        return int(self.image.shape[0]), int(self.image.shape[1])

    def draw_batch(self, generator: torch.Generator) -> dict[str, torch.Tensor]:
        index = torch.randint(0, self.rgb.shape[0], (self.batch_size,), generator=generator)
        return {"xy": self.xy[index], "rgb": self.rgb[index]}

    def val_dataloader(self) -> DataLoader:
        height, width = self.image_size
        whole: dict[str, Any] = {"xy": self.xy, "image": self.image, "height": height, "width": width}
        return DataLoader([whole], batch_size=None, num_workers=0)
