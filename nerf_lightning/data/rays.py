"""Batches of random rays drawn over all pixels of all training views, for fitting a radiance field."""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import torch

from nerf_lightning.data.batches import HeldOutView, RayBatch
from nerf_lightning.data.image_stack import as_float_rgb
from nerf_lightning.data.masks import composite_background
from nerf_lightning.data.scene import Scene
from nerf_lightning.data.scene_data import SceneDataModule, view_batch
from nerf_lightning.geometry.cameras import box_pixel_rectangles
from nerf_lightning.geometry.rays import indexed_pixel_rays

__all__ = ["RayDataModule", "view_batch"]


class RayDataModule(SceneDataModule):
    """Each training step ``batch_size`` rays drawn uniformly, with replacement, over every pixel of every
    training view, with their colours; the scene, its space, validation and render paths as every
    :class:`~nerf_lightning.data.scene_data.SceneDataModule` has them.

    Training batch: ``rays_o``, ``rays_d`` (N, 3) (unit directions, OpenCV cameras, world units), ``rgb``
    (N, 3) in [0, 1] and ``camera_index`` (N,), the training view of each ray; where the scene has depth, ``depth``
    (N,) the distance along each ray to its surface (NaN unknown, inf none); with ``data.masks=background``,
    ``mask`` (N,) bool too, the colour the background where it is False (:mod:`~nerf_lightning.data.masks`; with
    ``exclude`` the rays are drawn among the masked pixels alone). Where the scene has an object's box
    (``data.object_box``), among the pixels of each view's rectangle that holds the box's image alone: a ray that
    misses the box meets no sample, so its colour is the background whatever the field, and it teaches nothing.
    Validation batch:
    :func:`~nerf_lightning.data.scene_data.view_batch` of one view. The loader yields only the drawn pixels'
    indices (``pixel_index`` (N,)); once Lightning has moved them to the model's device,
    :meth:`on_after_batch_transfer` computes the rays there from the cameras of those pixels
    (:func:`~nerf_lightning.geometry.rays.indexed_pixel_rays`) and gathers their colours from the uint8 images,
    which are uploaded to a GPU once when they take less than a quarter of its free memory (else gathered on the
    host). Memory holds the training images (or, with ``data.scene.image_cache``, maps them from disk) and
    nothing per pixel besides.

    Args:
        batch_size: rays per training step.
        object_share: with ``data.masks=background``, the share of each batch's rays drawn among the masks' pixels
            (the rest as above, over the whole views): a capture whose object fills a small part of its photos
            still spends most rays on it, while the rest keep the room empty. None: no share set aside.
        scene, root, val_views, val_split, render_path, render_frames, ndc, contract, masks, val_steps, val_every, seed:
            see :class:`~nerf_lightning.data.scene_data.SceneDataModule`.
    """

    def __init__(self, scene: Callable[..., Scene], root: str | None = None, batch_size: int = 10_000,
                 object_share: float | None = None, **options: Any) -> None:
        super().__init__(scene, root, batch_size, **options)
        if object_share is not None and not 0.0 <= object_share <= 1.0:
            raise ValueError(f"data.object_share is the share of each batch's rays drawn on the object: a number in [0, 1] or null, got {object_share}")
        self.object_share = object_share

    def setup(self, stage: str | None = None) -> None:
        super().setup(stage)
        self.rgb = self.scene.train.images.reshape(-1, 3)  # (N*H*W, 3) uint8, a view of the images (in memory or mapped): no copy
        self.drawable: torch.Tensor | None = None  # (P,) the pixels rays are drawn from where not all of them
        self.rectangles: torch.Tensor | None = None  # (V, 4) x0, y0, x1, y1: each view's pixels rays are drawn from
        self.object_pixels: torch.Tensor | None = None  # (P,) the masks' pixels, which data.object_share draws from
        if self.object_share and self.mask_mode != "background":
            raise ValueError(f"data.object_share={self.object_share} draws rays on an object's masks, which need data.masks=background "
                             f"(masks in use: {self.mask_mode or 'none'}); set data.object_share=null")
        if self.mask_mode == "exclude" or self.object_share:
            pixels = masked_pixels(self.scene.train.masks)
            if not len(pixels):
                raise ValueError(f"data.masks={self.mask_mode}: the masks of {self.scene.source or 'the scene'} cover no pixel of the training views")
            if self.mask_mode == "exclude":
                self.drawable = pixels
            else:
                self.object_pixels = pixels
        if self.mask_mode != "exclude" and self.space.bounds is not None:
            train = self.scene.train
            self.rectangles = box_pixel_rectangles(train.K, train.c2w, train.height, train.width, self.space.bounds)

    def set_rays_per_batch(self, rays: int) -> None:
        """The rays of the batches drawn from now on (``data.batch_size`` at the start): how a sample budget
        (:class:`~nerf_lightning.models.ray_budget.RayBudget`) sizes the steps; a batch drawn already keeps its size."""
        if isinstance(rays, bool) or not isinstance(rays, int) or rays < 1:
            raise ValueError(f"rays a batch must be an integer >= 1, got {rays!r}")
        self.batch_size = rays

    def draw_batch(self, generator: torch.Generator) -> dict[str, torch.Tensor]:
        """``pixel_index`` (N,): pixels drawn uniformly, with replacement, over every training view (with
        ``data.masks=exclude``, over their masked pixels; with an object's box, over the pixels of the rectangles
        that hold its image; with ``data.object_share``, that share of them among the masks' pixels; see the class)."""
        on_object = 0 if self.object_pixels is None else round(self.object_share * self.batch_size)
        drawn = self._draw_pixels(self.batch_size - on_object, generator)
        if on_object:
            drawn = torch.cat([self.object_pixels[torch.randint(0, len(self.object_pixels), (on_object,), generator=generator)].long(), drawn])
        return {"pixel_index": drawn}

    def _draw_pixels(self, count: int, generator: torch.Generator) -> torch.Tensor:
        """(count,) pixels drawn uniformly over the masked pixels (``exclude``), the rectangles that hold the
        object's box, or every pixel of every training view."""
        if self.rectangles is not None:
            x0, y0, x1, y1 = self.rectangles.unbind(1)
            view = torch.multinomial(((x1 - x0) * (y1 - y0)).double(), count, replacement=True, generator=generator) if count else x0[:0]
            u, v = torch.rand(2, count, generator=generator, dtype=torch.float64)
            column = x0[view] + (u * (x1 - x0)[view]).long().clamp(max=(x1 - x0 - 1)[view])
            row = y0[view] + (v * (y1 - y0)[view]).long().clamp(max=(y1 - y0 - 1)[view])
            return (view * self.scene.train.height + row) * self.scene.train.width + column
        if self.drawable is not None:
            return self.drawable[torch.randint(0, len(self.drawable), (count,), generator=generator)].long()
        return torch.randint(0, self.rgb.shape[0], (count,), generator=generator)

    def on_after_batch_transfer(self, batch: dict[str, Any], dataloader_idx: int) -> RayBatch | HeldOutView:
        """A training batch's rays and colours (:class:`~nerf_lightning.data.batches.RayBatch`), made on the device
        its ``pixel_index`` was moved to."""
        if "pixel_index" not in batch:
            return batch  # a validation view: its camera, which the model renders
        index = batch["pixel_index"]
        K, c2w, images = self.cameras_and_images(index.device)
        rays_o, rays_d = indexed_pixel_rays(K, c2w, self.scene.train.height, self.scene.train.width, index)
        colours = self.rgb[index.cpu()].to(index.device, non_blocking=True) if images is None else images.reshape(-1, 3)[index]
        camera_index = index // (self.scene.train.height * self.scene.train.width)
        rays: RayBatch = {"rays_o": rays_o, "rays_d": rays_d, "rgb": as_float_rgb(colours), "camera_index": camera_index}
        depth = self.train_depth(index.device)
        if depth is not None:  # a capture's depth maps: what a depth loss (model.depth_loss) reads
            depth = depth.reshape(-1)
            rays["depth"] = depth[index.cpu()].to(index.device, non_blocking=True) if depth.device != index.device else depth[index]
        if self.mask_mode == "background":  # the pixels outside the object show the background; the model sees which
            masks = self.train_masks(index.device).reshape(-1)
            rays["object_mask"] = masks[index.cpu()].to(index.device, non_blocking=True) if masks.device != index.device else masks[index]
            rays["rgb"] = composite_background(rays["rgb"], rays["object_mask"], self.background_on(index.device))
        return rays


def masked_pixels(masks: torch.Tensor) -> torch.Tensor:
    """(P,) the indices of the True pixels of masks (V, H, W), flattened view by view, row-major; int32 where they
    fit (half the memory of int64), built view by view so that nonzero's int64 list is one view's at a time."""
    pixels = masks.shape[1] * masks.shape[2]
    index_type = torch.int32 if masks.numel() < 2**31 else torch.int64
    return torch.cat([torch.nonzero(mask.reshape(-1)).squeeze(1).to(index_type) + view * pixels for view, mask in enumerate(masks)])
