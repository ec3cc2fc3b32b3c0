"""Fitting a radiance field to posed images: a field, a sampler and a renderer in one scene space."""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import torch
import torch.nn.functional as F
from torch import nn
from torchmetrics import MeanMetric

from nerf_lightning.geometry.refinement import CameraRefinement
from nerf_lightning.geometry.space import SceneSpace
from nerf_lightning.metrics import image_metrics, mse_to_psnr
from nerf_lightning.models.base import FieldModule
from nerf_lightning.rendering.renderer import VolumeRenderer
from nerf_lightning.rendering.samplers.base import RaySampler


class RadianceFieldModule(FieldModule):
    """Trains a radiance field on random rays with an MSE loss on the rendered colour, plus the sampler's own losses.

    A ray goes through the scene space (:class:`~nerf_lightning.geometry.space.SceneSpace`, taken from the
    DataModule when fitting starts and kept in checkpoints), the sampler, the field and the renderer. Logs
    ``train/loss``, ``train/psnr``, ``train/samples_per_ray`` and each sampler loss ``train/loss_<name>`` every step
    (and the field's appearance penalty, ``train/loss_appearance``, when it has one);
    ``val/psnr``, ``val/ssim`` and, where the scene has true depth, ``val/depth_error`` over whole held-out views
    (:func:`~nerf_lightning.metrics.image_metrics`).

    Args:
        field: the radiance field (:class:`~nerf_lightning.fields.base.Field`).
        sampler: where along each ray the field is evaluated (:class:`~nerf_lightning.rendering.samplers.base.RaySampler`).
        optimizer, scheduler: see :class:`~nerf_lightning.models.base.FieldModule`; they train the field and
            whatever the sampler learns by gradient (a coarse network, proposal networks).
        renderer: the :class:`~nerf_lightning.rendering.renderer.VolumeRenderer` (its early stop and round size).
        chunk_size: rays rendered at once in evaluation, so memory stays bounded at any resolution.
        camera_refinement: learn a pose correction for each training view
            (:class:`~nerf_lightning.geometry.refinement.CameraRefinement`, its own learning rate, its penalties
            logged as ``train/loss_camera_*``); None keeps the poses as loaded.
        train_background: what a training ray shows where it is not opaque: ``scene`` (the scene space's
            background, as rendered) or ``random`` (a uniform random colour a ray and a step, Instant-NGP's): with
            photos that are opaque everywhere (a real capture) a transparent ray then cannot match its pixel, so the
            field learns surfaces instead of a fog. Not for photos that had alpha: their targets show the background.
    """

    kind = "radiance_field"

    def __init__(
        self,
        field: nn.Module,
        sampler: RaySampler,
        optimizer: Callable[..., torch.optim.Optimizer],
        scheduler: Callable[..., Any] | None = None,
        renderer: VolumeRenderer | None = None,
        chunk_size: int = 4096,
        camera_refinement: CameraRefinement | None = None,
        train_background: str = "scene",
    ) -> None:
        super().__init__(optimizer, scheduler)
        self.field, self.sampler = field, sampler
        self.renderer = renderer or VolumeRenderer()
        self.chunk_size = chunk_size
        self.camera_refinement = camera_refinement
        if train_background not in ("scene", "random"):
            raise ValueError(f"model.train_background must be scene or random, got '{train_background}'")
        self.train_background = train_background
        self.space = SceneSpace()
        # the mean over the validated views where a surface is seen (NaN views left out), summed over DDP ranks
        self.val_depth_error = MeanMetric(nan_strategy="ignore")

    def use_space(self, space: SceneSpace) -> None:
        """Render in ``space`` from now on; a box of a field or grid that cannot hold it is refused by name."""
        for name, module in self.named_modules():
            aabb = getattr(module, "aabb", None)
            if name and isinstance(aabb, torch.Tensor):
                space.check_box(aabb, f"model.{name}.aabb")
        self.space = space.to(self.device)

    def setup(self, stage: str) -> None:
        """Size what is learnt a training view (the field's appearance embedding, the camera corrections) to the
        training views (before the optimiser is built and a checkpoint is restored)."""
        scene = getattr(getattr(getattr(self, "trainer", None), "datamodule", None), "scene", None)
        for per_view in (getattr(self.field, "appearance", None), self.camera_refinement):
            if per_view is not None and scene is not None:
                per_view.resize(len(scene.train))

    def parameter_groups(self) -> Any:
        """The camera corrections, if any, in their own group at their own learning rate; the rest at the optimiser's."""
        if self.camera_refinement is None:
            return self.parameters()
        refinement = {id(p) for p in self.camera_refinement.parameters()}
        return [{"params": [p for p in self.parameters() if id(p) not in refinement]},
                {"params": list(self.camera_refinement.parameters()), "lr": self.camera_refinement.lr}]

    def on_fit_start(self) -> None:
        space = getattr(getattr(self.trainer, "datamodule", None), "space", None)
        if space is not None:
            self.use_space(space)

    def render(self, rays_o: torch.Tensor, rays_d: torch.Tensor, perturb: bool = False, camera_indices: torch.Tensor | None = None) -> dict[str, Any]:
        """(N, 3) world rays with unit directions (and (N,) the training image of each, or None for other views) ->
        rgb (N, 3), depth (N,), accumulation (N,), and the renderer's ``weights`` and ``n_evaluated`` and the
        sampler's ``samples`` (see :class:`VolumeRenderer`)."""
        rays = self.space.rays(rays_o, rays_d)._replace(camera_indices=camera_indices)
        samples = self.sampler.sample(rays, self.space, self.field, perturb)
        out = self.renderer(self.field, rays, samples, self.space)
        out["samples"] = samples
        return out

    @torch.no_grad()
    def render_chunked(self, rays_o: torch.Tensor, rays_d: torch.Tensor, chunk_size: int | None = None,
                       abort: Callable[[], bool] | None = None) -> dict[str, torch.Tensor] | None:
        """Evaluation render of any number of rays, ``chunk_size`` (default: the module's) at a time: rgb, depth,
        accumulation; None when ``abort()`` turns true between two chunks (the viewer, when its camera moves on)."""
        size = chunk_size or self.chunk_size
        keys = ("rgb", "depth", "accumulation")
        parts = {key: [] for key in keys}
        for origins, directions in zip(rays_o.split(size), rays_d.split(size)):
            if abort is not None and abort():
                return None
            out = self.render(origins, directions)
            for key in keys:  # only these: a chunk's samples and weights go with the next chunk (a fern frame's were 1 GB)
                parts[key].append(out[key])
        return {key: torch.cat(parts[key]) for key in keys}

    def training_step(self, batch: dict[str, torch.Tensor], batch_idx: int) -> torch.Tensor:
        self.sampler.update(self.global_step, self.field)
        rays_o, rays_d, camera_index = batch["rays_o"], batch["rays_d"], batch.get("camera_index")
        if self.camera_refinement is not None and camera_index is not None:
            rays_o, rays_d = self.camera_refinement(rays_o, rays_d, camera_index)
        out = self.render(rays_o, rays_d, perturb=True, camera_indices=camera_index)
        rgb = out["rgb"]
        if self.train_background == "random":  # what a ray leaves transparent shows a random colour, not the photo's
            rgb = rgb + (1.0 - out["accumulation"])[:, None] * (torch.rand_like(rgb) - self.space.background.to(rgb))
        mse = F.mse_loss(rgb, batch["rgb"])
        extra_losses = self.sampler.losses(out["samples"], out, batch["rgb"])
        if self.camera_refinement is not None:
            extra_losses.update(self.camera_refinement.penalties())
        appearance = getattr(self.field, "appearance", None)
        if appearance is not None:
            extra_losses.update(appearance.penalties())
        loss = mse + sum(extra_losses.values())
        if not loss.requires_grad:  # no ray of the batch met an occupied cell: nothing to learn, but the step goes on
            loss = loss + sum(parameter.sum() for parameter in self.parameters()) * 0.0
        self.log("train/samples_per_ray", float(out["n_evaluated"]) / batch["rays_o"].shape[0], on_step=True)
        for name, value in extra_losses.items():
            self.log(f"train/loss_{name}", value.detach(), on_step=True)
        self.log("train/loss", loss, on_step=True, on_epoch=False)
        self.log("train/psnr", mse_to_psnr(mse.detach()), on_step=True, prog_bar=True)
        return loss

    def validation_step(self, batch: dict[str, Any], batch_idx: int) -> dict[str, Any]:
        height, width = batch["height"], batch["width"]
        out = self.render_chunked(batch["rays_o"], batch["rays_d"])
        rgb, depth = out["rgb"].reshape(height, width, 3), out["depth"].reshape(height, width)
        target = batch["rgb"].reshape(height, width, 3)
        true_depth = batch["depth"].reshape(height, width) if "depth" in batch else None
        metrics = image_metrics(rgb, target, depth, true_depth)
        self.log("val/psnr", metrics["psnr"], prog_bar=True, batch_size=1, sync_dist=True)
        self.log("val/ssim", metrics["ssim"], batch_size=1, sync_dist=True)
        if "depth_error" in metrics:  # every rank validates views of the same scene: all log the key, or none does
            self.val_depth_error.update(metrics["depth_error"])
            self.log("val/depth_error", self.val_depth_error, batch_size=1)
        picture = self.space.depth_picture(depth) * out["accumulation"].reshape(height, width)
        return {"images": {"rgb": rgb, "depth": picture, "target": target}}

    def on_save_checkpoint(self, checkpoint: dict[str, Any]) -> None:
        super().on_save_checkpoint(checkpoint)
        checkpoint["scene_space"] = self.space.state()

    def on_load_checkpoint(self, checkpoint: dict[str, Any]) -> None:
        super().on_load_checkpoint(checkpoint)
        if checkpoint.get("scene_space"):
            self.space = SceneSpace.from_state(checkpoint["scene_space"]).to(self.device)
