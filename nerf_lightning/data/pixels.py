"""Batches of random pixels of one image, for fitting an image field."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import lightning as L
import torch
from torch.utils.data import DataLoader

from nerf_lightning.data.batches import SegmentedBatches, steps_to_next_validation
from nerf_lightning.data.images import default_image, downscale, load_image, pixel_grid


class PixelDataModule(L.LightningDataModule):
    """Each training step a batch of ``batch_size`` random pixels of one image; validation sees it whole.

    Training batch: ``xy`` (N, 2) pixel-centre positions, x divided by the width and y by the height, in
    [0, 1]; ``rgb`` (N, 3) colours in [0, 1] (8-bit values / 255). Pixels are drawn uniformly with
    replacement. Validation batch: every pixel in row-major order plus ``height`` and ``width``.

    Args:
        path: a PNG or JPG; None uses the built-in :func:`default_image`.
        batch_size: pixels per training step.
        downscale: integer factor, area averaging.
        val_steps: steps after which to validate (and take snapshots); the last step always validates.
        val_every: also validate every this many steps (None: only at ``val_steps``).
        max_steps: the trainer's step budget, so the last segment ends there.
        seed: seeds the pixel draws.
    """

    def __init__(
        self,
        path: str | None = None,
        batch_size: int = 10_000,
        downscale: int = 1,
        val_steps: list[int] | tuple[int, ...] = (10, 100, 200, 400, 1000),
        val_every: int | None = None,
        max_steps: int = 1000,
        seed: int = 0,
    ) -> None:
        super().__init__()
        if batch_size < 1:
            raise ValueError(f"data.batch_size must be >= 1, got {batch_size}")
        self.path = path
        self.batch_size = batch_size
        self.downscale_factor = downscale
        self.val_steps = sorted(int(s) for s in val_steps)
        self.val_every = val_every
        self.max_steps = max_steps
        self.seed = seed
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

    def _steps_done(self) -> int:
        return self.trainer.global_step if self.trainer is not None else 0

    def _rank(self) -> int:
        return self.trainer.global_rank if self.trainer is not None else 0

    def train_dataloader(self) -> DataLoader:
        batches = SegmentedBatches(
            self.draw_batch,
            steps_done=self._steps_done,
            segment_length=lambda step: steps_to_next_validation(step, self.val_steps, self.val_every, self.max_steps),
            seed=self.seed,
            rank=self._rank,
        )
        return DataLoader(batches, batch_size=None, num_workers=0)

    def val_dataloader(self) -> DataLoader:
        height, width = self.image_size
        whole: dict[str, Any] = {"xy": self.xy, "rgb": self.rgb, "height": height, "width": width}
        return DataLoader([whole], batch_size=None, num_workers=0)
