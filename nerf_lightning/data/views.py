"""Whole training views (or square patches of them), one a step, for models that render an image at a time."""

from __future__ import annotations

import logging
from collections.abc import Callable, Sequence
from typing import Any

import torch

from nerf_lightning.data.batches import HeldOutView, ViewBatch
from nerf_lightning.data.image_stack import as_float_rgb
from nerf_lightning.data.images import downscale, downscale_depth, downscale_mask
from nerf_lightning.data.masks import composite_background
from nerf_lightning.data.scene import Scene
from nerf_lightning.data.scene_data import SceneDataModule

log = logging.getLogger(__name__)

# the smallest side a coarse view is averaged down to
MIN_COARSE_SIDE = 16


def patch_camera(K: torch.Tensor, x0: torch.Tensor | int, y0: torch.Tensor | int) -> torch.Tensor:
    """K (..., 3, 3) of a view -> K of its crop whose top-left pixel is column ``x0``, row ``y0``: the principal
    point moves by (-x0, -y0), so the crop's pixel (u, v) sees what the view's (u + x0, v + y0) sees."""
    K = K.clone()
    K[..., 0, 2] -= x0
    K[..., 1, 2] -= y0
    return K


class ViewDataModule(SceneDataModule):
    """Each training step one training view drawn uniformly, whole or a random ``patch_size`` x ``patch_size``
    patch of it; the scene, its space, validation and render paths as every
    :class:`~nerf_lightning.data.scene_data.SceneDataModule` has them.

    Training batch: ``image`` (h, w, 3) float in [0, 1], ``K`` (3, 3) (of the patch: its principal point shifted
    by ``offset``), ``c2w`` (4, 4), ``camera_index`` () the training view, ``offset`` (2,) long, the column and row
    of the patch's top-left pixel in the view ((0, 0) for a whole view), and ``height``, ``width`` (h, w: the
    view's size, or ``patch_size``); with ``data.masks=exclude``, ``mask`` (h, w) bool, the pixels the loss covers
    (with ``background`` the image shows the background colour outside the mask; :mod:`~nerf_lightning.data.masks`);
    where the scene has depth, ``depth`` (h, w) (NaN unknown, inf none). The loader yields only ``camera_index`` and
    ``offset``, drawn with the step's seeded generator (a resumed run draws the same); :meth:`on_after_batch_transfer` cuts the image and camera on
    the model's device from the training images, uploaded there once where they fit (see
    :meth:`~nerf_lightning.data.scene_data.SceneDataModule.cameras_and_images`), else cut on the host.
    Validation batch: :func:`~nerf_lightning.data.scene_data.view_batch` of one held-out view.

    Coarse views first (``coarse_scale`` > 1): for the first ``coarse_steps`` steps each batch is the whole view,
    area-averaged by ``coarse_scale`` (its image, mask and ``K``), with ``scale`` = ``coarse_scale`` in the batch;
    ``patch_size`` patches at full resolution after. A step then covers the whole object at a fraction of a full
    view's pixels, while what it learns first (colour, shape) needs no fine detail (DashGaussian's resolution
    schedule). Several steps down are lists: ``coarse_scale=[4, 2]``, ``coarse_steps=[500, 1500]`` averages by 4 until
    step 500, by 2 until step 1500. Decided by the trainer's step as the batch reaches the device, so a resumed run
    draws the same.

    Args:
        patch_size: the side of a random square patch in pixels; None for the whole view.
        coarse_scale: the whole views' downscale for the first ``coarse_steps`` steps (1: none), or a list of them,
            largest first.
        coarse_steps: the step until which coarse views are trained, or a list of them, one a scale, growing.
        scene, root, val_views, val_split, render_path, render_frames, ndc, contract, masks, val_steps, val_every, seed:
            see :class:`~nerf_lightning.data.scene_data.SceneDataModule`.
    """

    def __init__(self, scene: Callable[..., Scene], root: str | None = None, patch_size: int | None = None,
                 coarse_scale: int | Sequence[int] = 1, coarse_steps: int | Sequence[int] = 0, **options: Any) -> None:
        super().__init__(scene, root, batch_size=1, **options)
        if patch_size is not None and patch_size < 1:
            raise ValueError(f"data.patch_size must be >= 1 or null (whole views), got {patch_size}")
        self.patch_size = patch_size
        self.coarse_schedule = coarse_schedule(coarse_scale, coarse_steps)

    def setup(self, stage: str | None = None) -> None:
        super().setup(stage)
        train = self.scene.train
        if self.patch_size is not None and self.patch_size > min(train.height, train.width):
            raise ValueError(f"data.patch_size={self.patch_size} does not fit the {train.width}x{train.height} training views "
                             f"of {self.scene.source or 'the scene'}: at most {min(train.height, train.width)}, or null for whole views")
        for scale, steps in self.coarse_schedule:
            if steps > 0 and scale > min(train.height, train.width):
                raise ValueError(f"data.coarse_scale={scale} is larger than the {train.width}x{train.height} training views "
                                 f"of {self.scene.source or 'the scene'}")
        # a coarse view keeps at least MIN_COARSE_SIDE pixels a side (the loss's SSIM window needs 11): a preset sized
        # for 1008x756 views averages small ones (a test's, a thumbnail capture's) less, not to a few pixels
        largest = max(1, min(train.height, train.width) // MIN_COARSE_SIDE)
        if any(scale > largest for scale, _ in self.coarse_schedule):
            log.warning("data.coarse_scale %s lowered to at most %d for the %dx%d training views: a coarse view keeps "
                        "at least %d pixels a side", [scale for scale, _ in self.coarse_schedule], largest, train.width,
                        train.height, MIN_COARSE_SIDE)
            self.coarse_schedule = [(min(scale, largest), steps) for scale, steps in self.coarse_schedule]

    def scale_now(self) -> int:
        """The training views' downscale at the trainer's current step: the first scale of the coarse schedule whose
        step it has not reached, else 1."""
        done = self._steps_done()
        return next((scale for scale, until in self.coarse_schedule if done < until), 1)

    def draw_batch(self, generator: torch.Generator) -> dict[str, torch.Tensor]:
        """``camera_index`` () a training view drawn uniformly and ``offset`` (2,) the column and row of a
        uniformly drawn patch's top-left pixel ((0, 0) for whole views)."""
        train = self.scene.train
        camera_index = torch.randint(0, len(train), (), generator=generator)
        if self.patch_size is None:
            x0 = y0 = torch.zeros((), dtype=torch.long)
        else:
            x0 = torch.randint(0, train.width - self.patch_size + 1, (), generator=generator)
            y0 = torch.randint(0, train.height - self.patch_size + 1, (), generator=generator)
        # the same numbers as Python ints, which stay on the host: cutting the image on a GPU then never waits on it
        crop = (int(camera_index), int(x0), int(y0))
        return {"camera_index": camera_index, "offset": torch.stack([x0, y0]), "crop": crop}

    def on_after_batch_transfer(self, batch: dict[str, Any], dataloader_idx: int) -> ViewBatch | HeldOutView:
        """A training batch's image (or patch) and camera (:class:`~nerf_lightning.data.batches.ViewBatch`), made on
        the device its ``camera_index`` was moved to."""
        if "offset" not in batch:
            return batch  # a validation view: its camera, which the model renders
        index, offset = batch["camera_index"], batch["offset"]
        device = index.device
        K, c2w, images = self.cameras_and_images(device)
        train = self.scene.train
        height, width = (train.height, train.width) if self.patch_size is None else (self.patch_size, self.patch_size)
        view, x0, y0 = batch["crop"]
        scale = self.scale_now()
        if scale > 1:  # the whole view, averaged below
            height, width, x0, y0, offset = train.height, train.width, 0, 0, torch.zeros_like(offset)
        if images is None:  # too large for the device: cut on the host, move the patch alone
            image = train.images[view, y0 : y0 + height, x0 : x0 + width].to(device, non_blocking=True)
        else:
            image = images[view, y0 : y0 + height, x0 : x0 + width]
        drawn: ViewBatch = {"image": as_float_rgb(image), "K": patch_camera(K[view], x0, y0), "c2w": c2w[view],
                            "camera_index": index, "offset": offset, "height": height, "width": width}
        if self.mask_mode is not None:
            mask = self.train_masks(device)[view, y0 : y0 + height, x0 : x0 + width].to(device, non_blocking=True)
            if self.mask_mode == "background":  # the pixels outside the object show the background; the model sees which
                drawn["image"] = composite_background(drawn["image"], mask, self.scene.background)
                drawn["object_mask"] = mask
            else:  # exclude: the model's loss covers the masked pixels alone
                drawn["loss_mask"] = mask
        depth = self.train_depth(device)
        if depth is not None:  # a capture's depth maps: what a depth loss (model.loss.depth_loss) reads
            drawn["depth"] = depth[view, y0 : y0 + height, x0 : x0 + width].to(device, non_blocking=True)
        if scale > 1:
            drawn = coarse_view(drawn, scale)
        return drawn


def coarse_schedule(coarse_scale: int | Sequence[int], coarse_steps: int | Sequence[int]) -> list[tuple[int, int]]:
    """``data.coarse_scale`` and ``data.coarse_steps`` (a number each, or lists of one length) -> [(scale, until
    step)], checked: whole scales >= 1, largest first, and the steps they end at >= 0 and growing."""
    scales = list(coarse_scale) if isinstance(coarse_scale, Sequence) else [coarse_scale]
    steps = list(coarse_steps) if isinstance(coarse_steps, Sequence) else [coarse_steps]
    if len(scales) != len(steps):
        raise ValueError(f"data.coarse_scale and data.coarse_steps must have one step a scale, got {scales} and {steps}")
    if any(not isinstance(scale, (int, float)) or int(scale) != scale or scale < 1 for scale in scales) \
            or any(not isinstance(step, (int, float)) or int(step) != step or step < 0 for step in steps):
        raise ValueError(f"data.coarse_scale must be whole numbers >= 1 and data.coarse_steps whole numbers >= 0, got {scales} and {steps}")
    if scales != sorted(scales, reverse=True) or steps != sorted(steps):
        raise ValueError(f"data.coarse_scale must go down (coarsest first) and data.coarse_steps up, got {scales} and {steps}")
    return [(int(scale), int(step)) for scale, step in zip(scales, steps)]


def coarse_view(drawn: ViewBatch, scale: int) -> ViewBatch:
    """A whole view's batch area-averaged by ``scale``: its image (the object over the background already, with
    ``background`` masks), its masks (a pixel the object where half its block is) and its camera, whose focal lengths
    and principal point shrink with the pixels (the pixel centres' convention keeps the average exact); its depth, each
    block the mean of its known values."""
    K = drawn["K"].clone()
    K[..., :2, :] = K[..., :2, :] / scale
    coarse: ViewBatch = {**drawn, "image": downscale(drawn["image"], scale), "K": K, "scale": scale}
    for key in ("object_mask", "loss_mask"):
        if key in drawn:
            coarse[key] = downscale_mask(drawn[key], scale)
    if "depth" in drawn:
        coarse["depth"] = downscale_depth(drawn["depth"], scale)
    coarse["height"], coarse["width"] = coarse["image"].shape[:2]
    return coarse
