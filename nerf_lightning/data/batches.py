"""Random training batches, streamed in segments that end where validation is due.

Training is counted in optimiser steps, one random batch a step. Lightning validates an endless
iterable dataset when its iterator runs out, so each pass ("epoch") of the stream lasts until the next
validation step; validation then happens at exactly the steps asked for (for example 10, 100, 200, 400,
1000), not at a fixed interval. Each batch's random numbers are seeded from (seed, rank, step), so a run
resumed from a checkpoint draws the batches the uninterrupted run would have drawn.
"""

from __future__ import annotations

from collections.abc import Callable, Iterator, Sequence
from typing import Any, TypedDict

import lightning as L
import torch
from torch.utils.data import DataLoader, IterableDataset


# What the DataModules give a model, typed once. A capture's masks (data.masks) give the same keys in rays and views:
# ``object_mask`` (True on the object) where the mode is ``background`` (the pixels outside show the background
# colour), ``loss_mask`` (True where the loss reaches) for a view or patch where it is ``exclude`` (rays are then drawn
# among the masked pixels, and need none). A held-out view's ``object_mask`` is where it is scored alone.


class RayBatch(TypedDict, total=False):
    """A training step's random rays (``RayDataModule``), N of them, on the training device."""

    rays_o: torch.Tensor  # (N, 3) origins, in the scene's world
    rays_d: torch.Tensor  # (N, 3) directions (unit)
    rgb: torch.Tensor  # (N, 3) float in [0, 1], the pixels' colours
    camera_index: torch.Tensor  # (N,) long, the training view each ray is of
    object_mask: torch.Tensor  # (N,) bool, data.masks=background
    depth: torch.Tensor  # (N,) distance along each ray to its surface, NaN unknown, inf none; where the scene has depth


class ViewBatch(TypedDict, total=False):
    """A training step's whole view or patch (``ViewDataModule``), h x w pixels, on the training device."""

    image: torch.Tensor  # (h, w, 3) float in [0, 1]
    K: torch.Tensor  # (3, 3) the patch's intrinsics (its principal point moved by the offset)
    c2w: torch.Tensor  # (4, 4) OpenCV camera-to-world
    camera_index: torch.Tensor  # () long
    offset: torch.Tensor  # (2,) long, the patch's first column and row in the view
    height: int
    width: int
    object_mask: torch.Tensor  # (h, w) bool, data.masks=background
    loss_mask: torch.Tensor  # (h, w) bool, data.masks=exclude
    scale: int  # a coarse view's downscale (data.coarse_scale); absent: full resolution
    depth: torch.Tensor  # (h, w) distance along each pixel's unit ray, NaN unknown, inf none; where the scene has depth


class HeldOutView(TypedDict, total=False):
    """One whole held-out view, as validation and ``nerf-eval`` score it (:func:`~nerf_lightning.data.scene_data.view_batch`)."""

    K: torch.Tensor  # (3, 3)
    c2w: torch.Tensor  # (4, 4) OpenCV camera-to-world; a model renders it with render_view
    height: int
    width: int
    index: int  # in the views it is one of
    image: torch.Tensor  # (H, W, 3) float in [0, 1], where the views have images
    depth: torch.Tensor  # (H, W) distance along each pixel's unit ray (NaN unknown, inf none), where the scene has depth
    object_mask: torch.Tensor  # (H, W) bool, with masks and a masks mode


def steps_to_next_validation(step: int, val_steps: Sequence[int], val_every: int | None, max_steps: int) -> int:
    """Number of training steps from ``step`` (steps done so far) to the next validation.

    Validation is due after any step in ``val_steps``, after every multiple of ``val_every``, and after
    the last step ``max_steps`` (max_steps < 0 means no limit).
    """
    candidates = [s for s in val_steps if s > step]
    if val_every:
        candidates.append((step // val_every + 1) * val_every)
    if max_steps is not None and max_steps > 0:
        candidates.append(max_steps)
    if not candidates:
        raise ValueError("training has no end and no validation steps: set trainer.max_steps, data.val_steps or data.val_every")
    return max(1, min(candidates) - step)


def batch_seed(seed: int, rank: int, step: int) -> int:
    """The seed of the random batch of optimiser step ``step`` on process ``rank``."""
    return hash((seed, rank, step)) & 0x7FFF_FFFF_FFFF_FFFF


class SegmentedBatches(IterableDataset):
    """An iterable dataset whose every pass yields the batches up to the next validation step.

    Args:
        draw_batch: draws one batch with the given generator.
        steps_done: returns the number of optimiser steps taken so far (the trainer's global step).
        segment_length: maps the steps done to the length of the next segment.
        seed: base seed; the batch of step s is drawn with a generator seeded from (seed, rank, s).
        rank: the process rank, so data-parallel processes draw different batches.
    """

    def __init__(
        self,
        draw_batch: Callable[[torch.Generator], dict[str, Any]],
        steps_done: Callable[[], int],
        segment_length: Callable[[int], int],
        seed: int,
        rank: Callable[[], int] = lambda: 0,
    ) -> None:
        super().__init__()
        self.draw_batch = draw_batch
        self.steps_done = steps_done
        self.segment_length = segment_length
        self.seed = seed
        self.rank = rank

    def __iter__(self) -> Iterator[dict[str, Any]]:
        start, rank = self.steps_done(), self.rank()
        generator = torch.Generator()
        for step in range(start, start + self.segment_length(start)):
            generator.manual_seed(batch_seed(self.seed, rank, step))
            yield self.draw_batch(generator)


class StepBatchesDataModule(L.LightningDataModule):
    """A DataModule whose training set is one random batch a step, validated at chosen steps.

    Subclasses load their data in ``setup`` and implement :meth:`draw_batch` and ``val_dataloader``.

    Args:
        batch_size: samples (pixels, rays) per training step.
        val_steps: steps after which to validate; the last step (the trainer's ``max_steps``) always validates.
        val_every: also validate every this many steps (None: only at ``val_steps``).
        seed: seeds the batches; each process of a data-parallel run draws its own.
    """

    def __init__(self, batch_size: int, val_steps: Sequence[int] = (), val_every: int | None = None, seed: int = 0) -> None:
        super().__init__()
        if batch_size < 1:
            raise ValueError(f"data.batch_size must be >= 1, got {batch_size}")
        if val_every is not None and val_every < 1:
            raise ValueError(f"data.val_every must be >= 1 or null, got {val_every}")
        self.batch_size = batch_size
        self.val_steps = sorted(int(step) for step in val_steps)
        self.val_every = val_every
        self.seed = seed

    def draw_batch(self, generator: torch.Generator) -> dict[str, Any]:
        """One training batch, drawn with ``generator``."""
        raise NotImplementedError

    def _steps_done(self) -> int:
        return self.trainer.global_step if self.trainer is not None else 0

    def _rank(self) -> int:
        return self.trainer.global_rank if self.trainer is not None else 0

    def _max_steps(self) -> int:
        return self.trainer.max_steps if self.trainer is not None else -1

    def segment_length(self, step: int) -> int:
        """Training steps from ``step`` to the next validation."""
        if self.trainer is None:  # iterated outside a Trainer (tests, notebooks): one segment up to the next validation
            return steps_to_next_validation(step, self.val_steps, self.val_every or 1_000_000, -1)
        return steps_to_next_validation(step, self.val_steps, self.val_every, self._max_steps())

    def train_dataloader(self) -> DataLoader:
        batches = SegmentedBatches(self.draw_batch, steps_done=self._steps_done, segment_length=self.segment_length, seed=self.seed, rank=self._rank)
        return DataLoader(batches, batch_size=None, num_workers=0, pin_memory=self._pins_memory())

    def _pins_memory(self) -> bool:
        """Batches in page-locked memory when training on a CUDA device: Lightning then copies them there without
        waiting (a copy from ordinary memory makes the host wait for the device to finish what it was given)."""
        device = getattr(getattr(self.trainer, "strategy", None), "root_device", None)
        return getattr(device, "type", None) == "cuda"
