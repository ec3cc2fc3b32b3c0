"""Fitting a radiance field to posed images."""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import kornia
import torch
import torch.nn.functional as F
from torch import nn

from nerf_lightning.geometry.rays import ndc_rays
from nerf_lightning.metrics import mse_to_psnr
from nerf_lightning.models.base import FieldModule
from nerf_lightning.rendering.occupancy import OccupancyGrid
from nerf_lightning.rendering.renderer import render_rays, render_rays_marched


class RadianceFieldModule(FieldModule):
    """Trains a radiance field on random rays with an MSE loss on the rendered colour.

    Logs ``train/loss`` and ``train/psnr`` every step; ``val/psnr``, ``val/ssim`` (kornia) and, where the scene
    has true depth, ``val/depth_error`` (mean absolute error in scene units over pixels that see a surface)
    over whole held-out views. Near, far, the background and ``world_from_capture`` (the similarity from the
    capture's coordinates to the scene's, or None) come from the scene at the start of fitting and are kept in
    checkpoints.

    Args:
        field: the (coarse) field: ``field(points, directions) -> {"rgb", "density"}``, with ``density(points)``.
        optimizer, scheduler: see :class:`~nerf_lightning.models.base.FieldModule`.
        fine_field: the fine network of hierarchical sampling; None for a single network.
        n_samples: stratified samples per ray.
        n_fine_samples: importance samples per ray for the fine network.
        chunk_size: rays rendered at once in evaluation, so memory stays bounded at any resolution.
        occupancy_grid: empty-space skipping: rays are marched through the grid's occupied cells (packed
            samples, see :func:`~nerf_lightning.rendering.renderer.render_rays_marched`) instead of sampled at
            ``n_samples`` points, and the grid is refreshed from ``field.density`` as training goes. Works with
            any field; not with a fine field.
        render_step_size: the marcher's step; None for (far - near) / n_samples, the stratified spacing.
        alpha_threshold, early_stop_eps, samples_per_round: see :func:`~nerf_lightning.rendering.renderer.render_rays_marched`:
            a ray stops being evaluated once its transmittance is below ``early_stop_eps``, checked every
            ``samples_per_round`` samples; ``alpha_threshold`` > 0 drops nearly transparent samples too.
        cone_angle: > 0 makes the marcher's steps grow with the distance, ``max(step, cone_angle * t)``, for
            unbounded scenes (a contracted field and grid), whose background reaches far.
    """

    kind = "radiance_field"

    def __init__(
        self,
        field: nn.Module,
        optimizer: Callable[..., torch.optim.Optimizer],
        scheduler: Callable[..., Any] | None = None,
        fine_field: nn.Module | None = None,
        n_samples: int = 64,
        n_fine_samples: int = 0,
        chunk_size: int = 4096,
        occupancy_grid: OccupancyGrid | None = None,
        render_step_size: float | None = None,
        alpha_threshold: float = 0.0,
        early_stop_eps: float = 1e-4,
        samples_per_round: int = 16,
        cone_angle: float = 0.0,
    ) -> None:
        super().__init__(optimizer, scheduler)
        if occupancy_grid is not None and fine_field is not None and n_fine_samples > 0:
            raise ValueError("model: occupancy_grid replaces hierarchical sampling; set model.fine_field=null or model.occupancy_grid=null")
        self.field = field
        self.fine_field = fine_field
        self.n_samples = n_samples
        self.n_fine_samples = n_fine_samples if fine_field is not None else 0
        self.chunk_size = chunk_size
        self.occupancy_grid = occupancy_grid
        self.render_step_size, self.alpha_threshold, self.early_stop_eps = render_step_size, alpha_threshold, early_stop_eps
        self.samples_per_round, self.cone_angle = samples_per_round, cone_angle
        self.near, self.far = 2.0, 6.0
        self.ndc: dict[str, float] | None = None  # NDC parameters of a forward-facing scene (data.ndc=true)
        self.world_from_capture: torch.Tensor | None = None
        self.register_buffer("background", torch.ones(3))

    def on_fit_start(self) -> None:
        scene = getattr(getattr(self.trainer, "datamodule", None), "scene", None)
        if scene is not None:
            self.near, self.far = float(scene.near), float(scene.far)
            self.background.copy_(scene.background)
            self.world_from_capture = scene.world_from_capture
            self.ndc = getattr(self.trainer.datamodule, "ndc_params", None)
            if self.ndc:
                self.near, self.far = 0.0, 1.0  # NDC rays run from the near plane (t = 0) to infinity (t = 1)

    @property
    def step_size(self) -> float:
        """The marcher's step in ray t: world units along unit rays, or NDC t (0 to 1) with ``ndc``."""
        return self.render_step_size or (self.far - self.near) / self.n_samples

    def render(self, rays_o: torch.Tensor, rays_d: torch.Tensor, perturb: bool = False) -> dict[str, torch.Tensor]:
        """(N, 3) world rays with unit directions -> rgb (N, 3), depth (N,), accumulation (N,) and more; see
        :func:`render_rays`. With ``ndc`` the rays are sampled in NDC and the field sees the world directions."""
        directions = rays_d
        if self.ndc:
            rays_o, rays_d = ndc_rays(rays_o, rays_d, self.ndc["focal"], self.ndc["width"], self.ndc["height"], self.ndc["near_plane"])
        if self.occupancy_grid is not None:
            return render_rays_marched(
                self.field, self.occupancy_grid, rays_o, rays_d, self.near, self.far, self.step_size, perturb, self.background,
                self.alpha_threshold, self.early_stop_eps, self.samples_per_round, directions=directions, cone_angle=self.cone_angle,
            )
        return render_rays(
            self.field, rays_o, rays_d, self.near, self.far, self.n_samples, perturb, self.background,
            fine_field=self.fine_field, n_fine_samples=self.n_fine_samples, directions=directions,
        )

    @torch.no_grad()
    def render_chunked(self, rays_o: torch.Tensor, rays_d: torch.Tensor) -> dict[str, torch.Tensor]:
        """Evaluation render of any number of rays, ``chunk_size`` at a time: rgb, depth, accumulation."""
        parts = [self.render(o, d) for o, d in zip(rays_o.split(self.chunk_size), rays_d.split(self.chunk_size))]
        return {key: torch.cat([part[key] for part in parts]) for key in ("rgb", "depth", "accumulation")}

    def training_step(self, batch: dict[str, torch.Tensor], batch_idx: int) -> torch.Tensor:
        if self.occupancy_grid is not None:
            self.occupancy_grid.update(self.global_step, self.field.density, self.step_size)
        out = self.render(batch["rays_o"], batch["rays_d"], perturb=True)
        if "n_samples" in out:
            self.log("train/samples_per_ray", out["n_samples"].float() / batch["rays_o"].shape[0], on_step=True)
        mse = F.mse_loss(out["rgb"], batch["rgb"])
        loss = mse
        if "coarse_rgb" in out:
            coarse_mse = F.mse_loss(out["coarse_rgb"], batch["rgb"])
            loss = loss + coarse_mse
            self.log("train/psnr_coarse", mse_to_psnr(coarse_mse.detach()), on_step=True)
        self.log("train/loss", loss, on_step=True, on_epoch=False)
        self.log("train/psnr", mse_to_psnr(mse.detach()), on_step=True, prog_bar=True)
        return loss

    def depth_image(self, depth: torch.Tensor) -> torch.Tensor:
        """Depth as a picture in [0, 1], near bright: linear between near and far, or, for an unbounded scene (a
        contracted grid), contracted like the scene: 1 - d/2 up to d = 1 (the box's half-size), 1/(2d) beyond."""
        if self.occupancy_grid is not None and self.occupancy_grid.contracted:
            half_size = float((self.occupancy_grid.aabb[3:] - self.occupancy_grid.aabb[:3]).max()) / 2.0
            distance = depth / half_size
            return torch.where(distance <= 1.0, 1.0 - distance / 2.0, 0.5 / distance.clamp(min=1.0))
        return (1.0 - (depth - self.near) / (self.far - self.near)).clamp(0.0, 1.0)

    def validation_step(self, batch: dict[str, Any], batch_idx: int) -> dict[str, Any]:
        height, width = batch["height"], batch["width"]
        out = self.render_chunked(batch["rays_o"], batch["rays_d"])
        rgb = out["rgb"].reshape(height, width, 3)
        target = batch["rgb"].reshape(height, width, 3)
        self.log("val/psnr", kornia.metrics.psnr(rgb, target, max_val=1.0), prog_bar=True, batch_size=1, sync_dist=True)
        ssim = kornia.metrics.ssim(rgb.permute(2, 0, 1)[None], target.permute(2, 0, 1)[None], window_size=11).mean()
        self.log("val/ssim", ssim, batch_size=1, sync_dist=True)
        if "depth" in batch:
            surface = torch.isfinite(batch["depth"])
            if surface.any():
                self.log("val/depth_error", (out["depth"][surface] - batch["depth"][surface]).abs().mean(), batch_size=1, sync_dist=True)
        depth = self.depth_image(out["depth"]) * out["accumulation"]
        return {"images": {"rgb": rgb, "depth": depth.reshape(height, width), "target": target}}

    def on_save_checkpoint(self, checkpoint: dict[str, Any]) -> None:
        super().on_save_checkpoint(checkpoint)
        world_from_capture = None if self.world_from_capture is None else self.world_from_capture.tolist()
        checkpoint["scene_bounds"] = {"near": self.near, "far": self.far, "ndc": self.ndc, "world_from_capture": world_from_capture}

    def on_load_checkpoint(self, checkpoint: dict[str, Any]) -> None:
        super().on_load_checkpoint(checkpoint)
        bounds = checkpoint.get("scene_bounds")
        if bounds:
            self.near, self.far = float(bounds["near"]), float(bounds["far"])
            self.ndc = bounds.get("ndc")
            if bounds.get("world_from_capture") is not None:
                self.world_from_capture = torch.tensor(bounds["world_from_capture"])
