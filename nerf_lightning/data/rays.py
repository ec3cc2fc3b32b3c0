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
from nerf_lightning.geometry.rays import indexed_pixel_rays

__all__ = ["RayDataModule", "view_batch"]


class RayDataModule(SceneDataModule):
    """Each training step ``batch_size`` rays drawn uniformly, with replacement, over every pixel of every
    training view, with their colours; the scene, its space, validation and render paths as every
    :class:`~nerf_lightning.data.scene_data.SceneDataModule` has them.

    Training batch: ``rays_o``, ``rays_d`` (N, 3) (unit directions, OpenCV cameras, world units), ``rgb``
    (N, 3) in [0, 1] and ``camera_index`` (N,), the training view of each ray; with ``data.masks=background``,
    ``mask`` (N,) bool too, the colour the background where it is False (:mod:`~nerf_lightning.data.masks`; with
    ``exclude`` the rays are drawn among the masked pixels alone). Validation batch:
    :func:`~nerf_lightning.data.scene_data.view_batch` of one view. The loader yields only the drawn pixels'
    indices (``pixel_index`` (N,)); once Lightning has moved them to the model's device,
    :meth:`on_after_batch_transfer` computes the rays there from the cameras of those pixels
    (:func:`~nerf_lightning.geometry.rays.indexed_pixel_rays`) and gathers their colours from the uint8 images,
    which are uploaded to a GPU once when they take less than a quarter of its free memory (else gathered on the
    host). Memory holds the training images (or, with ``data.scene.image_cache``, maps them from disk) and
    nothing per pixel besides.

    Args:
        batch_size: rays per training step.
        scene, root, val_views, val_split, render_path, render_frames, ndc, contract, masks, val_steps, val_every, seed:
            see :class:`~nerf_lightning.data.scene_data.SceneDataModule`.
    """

    def __init__(self, scene: Callable[..., Scene], root: str | None = None, batch_size: int = 10_000, **options: Any) -> None:
        super().__init__(scene, root, batch_size, **options)

    def setup(self, stage: str | None = None) -> None:
        super().setup(stage)
        self.rgb = self.scene.train.images.reshape(-1, 3)  # (N*H*W, 3) uint8, a view of the images (in memory or mapped): no copy
        self.drawable: torch.Tensor | None = None  # (P,) the pixels rays are drawn from where not all of them
        if self.mask_mode == "exclude":
            masks = self.scene.train.masks
            pixels = masks.shape[1] * masks.shape[2]
            index_type = torch.int32 if masks.numel() < 2**31 else torch.int64  # half the memory of a pixel list
            # view by view: nonzero's int64 list is then one view's at a time
            self.drawable = torch.cat([torch.nonzero(mask.reshape(-1)).squeeze(1).to(index_type) + view * pixels
                                       for view, mask in enumerate(masks)])
            if not len(self.drawable):
                raise ValueError(f"data.masks=exclude: the masks of {self.scene.source or 'the scene'} cover no pixel of the training views")

    def set_rays_per_batch(self, rays: int) -> None:
        """The rays of the batches drawn from now on (``data.batch_size`` at the start): how a sample budget
        (:class:`~nerf_lightning.models.ray_budget.RayBudget`) sizes the steps; a batch drawn already keeps its size."""
        if isinstance(rays, bool) or not isinstance(rays, int) or rays < 1:
            raise ValueError(f"rays a batch must be an integer >= 1, got {rays!r}")
        self.batch_size = rays

    def draw_batch(self, generator: torch.Generator) -> dict[str, torch.Tensor]:
        """``pixel_index`` (N,): pixels drawn uniformly, with replacement, over every training view (with
        ``data.masks=exclude``, over their masked pixels; see the class)."""
        if self.drawable is not None:
            return {"pixel_index": self.drawable[torch.randint(0, len(self.drawable), (self.batch_size,), generator=generator)].long()}
        return {"pixel_index": torch.randint(0, self.rgb.shape[0], (self.batch_size,), generator=generator)}

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
        if self.mask_mode == "background":  # the pixels outside the object show the background; the model sees which
            masks = self.train_masks(index.device).reshape(-1)
            rays["object_mask"] = masks[index.cpu()].to(index.device, non_blocking=True) if masks.device != index.device else masks[index]
            rays["rgb"] = composite_background(rays["rgb"], rays["object_mask"], self.background_on(index.device))
        return rays
