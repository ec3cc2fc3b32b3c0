"""Fitting a radiance field to posed images: a field, a sampler and a renderer in one scene space."""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import numpy as np
import torch
import torch.nn.functional as F
from torch import nn

from nerf_lightning.compiling import CompiledOrEager
from nerf_lightning.data.batches import RayBatch
from nerf_lightning.data.masks import composite_background
from nerf_lightning.data.views import ViewDataModule
from nerf_lightning.geometry.rays import image_rays
from nerf_lightning.geometry.refinement import CameraRefinement
from nerf_lightning.geometry.space import SceneSpace
from nerf_lightning.metrics import check_loss_weight, check_train_background, depth_l1, mse_to_psnr, opacity_mask_loss
from nerf_lightning.models.base import SceneModule, depth_for_depth_loss, masks_for_mask_loss
from nerf_lightning.models.contract import Overlay
from nerf_lightning.models.radiance_field_config import config_before_04
from nerf_lightning.parameters.exposure import ViewExposure
from nerf_lightning.rendering.renderer import Renderer, check_compilable
from nerf_lightning.rendering.rounds import RoundsRenderer
from nerf_lightning.rendering.samplers.base import RaySampler


# model.mask_loss=null's weight where the training batches carry masks (nerfacto_object_cpu's, measured on the cape:
# docs/guides/real-captures.md)
MASK_LOSS_WITH_MASKS = 0.01


class RadianceFieldModule(SceneModule):
    """Trains a radiance field on random rays with an MSE loss on the rendered colour, plus the sampler's own losses.

    Under the model contract (:mod:`nerf_lightning.models.contract`) it renders a camera (:meth:`render_view`), has
    a density to mesh (:meth:`density_at`, :meth:`colour_at`, :meth:`mesh_box`) and shows its box and its occupancy
    grid's occupied cells in the viewer (:meth:`overlay_names`, :meth:`overlay`).

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
        renderer: a :class:`~nerf_lightning.rendering.renderer.Renderer` (``model/renderer=...``).
        chunk_size: rays rendered at once in evaluation, so memory stays bounded at any resolution.
        camera_refinement: learn a pose correction for each training view
            (:class:`~nerf_lightning.geometry.refinement.CameraRefinement`, its own learning rate, its penalties
            logged as ``train/loss_camera_*``); None keeps the poses as loaded.
        exposure: learn each training photo's exposure and white balance
            (:class:`~nerf_lightning.parameters.exposure.ViewExposure`: three gains a photo, each training ray's colour,
            not the background, multiplied by its photo's; its own learning rate, its penalty logged as
            ``train/loss_exposure_appearance``); None: the photos as they are. Held-out views are rendered at the mean.
        train_background: what a training ray shows where it is not opaque: ``scene`` (the scene space's
            background, as rendered) or ``random`` (a uniform random colour a ray and a step, Instant-NGP's): with
            photos that are opaque everywhere (a real capture) a transparent ray then cannot match its pixel, so the
            field learns surfaces instead of a fog. Not for photos that had alpha: their targets show the background
            (but with ``data.masks=background`` the target outside the mask shows the same random colour).
        mask_loss: the weight of a binary cross-entropy between each training ray's opacity and its object mask
            (NeuS's mask loss; logged as ``train/loss_mask``), with ``data.masks=background``: the field is taught
            where the object ends by the masks themselves, not only by the background's colour, which a dark surface
            or a hole in the object (seen through, masked out) shares. 0: none. None: :data:`MASK_LOSS_WITH_MASKS`
            where the training batches carry masks (``data.masks=background``), none where they do not: with the
            colours alone, a capture whose views are mostly that black background can drive every density to zero in
            the first steps, where it stays.
        depth_loss: the weight of the mean absolute difference between each training ray's rendered depth and the
            capture's (its depth maps, :mod:`~nerf_lightning.data.formats.depth_maps`; logged as ``train/loss_depth``)
            over the rays whose depth is known: the geometry a phone's LiDAR measured, where the photos alone leave it
            loose. Not in NDC (``data.ndc``), whose distances are not the world's. 0: none.
        compile: run the training step's forward and loss (sampling, field, compositing, loss) as one graph through
            ``torch.compile(fullgraph=True)``, its backward compiled with it (inductor: C++ on a CPU, Triton kernels on
            a GPU); the sampler's grid refreshes stay outside. Only where no size in the step depends on the data
            (:func:`~nerf_lightning.rendering.renderer.check_compilable`, the GPU presets); without a working compiler it runs plainly after one warning (:class:`~nerf_lightning.compiling.CompiledOrEager`).
        compile_mode: ``torch.compile``'s mode (None: its default; ``reduce-overhead``: CUDA graphs on a GPU,
            ``max-autotune-no-cudagraphs``).
    """

    kind = "radiance_field"
    # a checkpoint's model config of before 0.4 read as this one's (models/radiance_field_config.py)
    upgrade_config = staticmethod(config_before_04)

    def __init__(
        self,
        field: nn.Module,
        sampler: RaySampler,
        optimizer: Callable[..., torch.optim.Optimizer],
        scheduler: Callable[..., Any] | None = None,
        renderer: Renderer | None = None,
        chunk_size: int = 4096,
        camera_refinement: CameraRefinement | None = None,
        exposure: ViewExposure | None = None,
        train_background: str = "scene",
        mask_loss: float | None = 0.0,
        depth_loss: float = 0.0,
        compile: bool = False,
        compile_mode: str | None = None,
    ) -> None:
        super().__init__(optimizer, scheduler)
        self.field, self.sampler = field, sampler
        self.renderer = renderer or RoundsRenderer()
        self.chunk_size = chunk_size
        self.camera_refinement, self.exposure = camera_refinement, exposure
        self.train_background = check_train_background(train_background)
        self.mask_loss = None if mask_loss is None else check_loss_weight(mask_loss, "model.mask_loss")
        self.depth_loss = check_loss_weight(depth_loss, "model.depth_loss")
        if compile:
            check_compilable(self.renderer, sampler)
        self.rays_that_fit: torch.Tensor | None = None  # see training_step
        # the function, not the bound method: a copy of the module would otherwise run this one's step
        self.compiled_step = CompiledOrEager(type(self).step_losses, "the training step", fullgraph=True, dynamic=None,
                                             mode=compile_mode) if compile else None

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
        datamodule = getattr(getattr(self, "trainer", None), "datamodule", None)
        if stage == "fit" and isinstance(datamodule, ViewDataModule):
            raise ValueError("a radiance field trains on random rays, and data=views serves whole "
                             "training views: use data=rays (with data/scene=<format>), which serves rays")
        precision = str(getattr(getattr(self, "trainer", None), "precision", "32-true"))
        for name, module in self.named_modules():
            if getattr(module, "table_precision", None) == torch.float16 and stage == "fit" and not precision.startswith("16"):
                raise ValueError(f"model.{name}.table_precision=float16 needs trainer.precision=16-mixed, whose loss scaling keeps "
                                 f"the table's small gradients from vanishing in float16 (got trainer.precision={precision}); "
                                 "or use table_precision=bfloat16")
        scene = getattr(datamodule, "scene", None)
        for per_view in (self.field.appearance, self.camera_refinement, self.exposure):
            if per_view is not None and scene is not None:
                per_view.resize(len(scene.train))

    def parameter_groups(self) -> list[dict[str, Any]]:
        """``field`` (the field and what the sampler learns) at the optimiser's learning rate, and the camera
        corrections and the photos' exposures, those that are on, in ``camera_refinement`` and ``exposure`` at their own."""
        own = {name: per_view for name in ("camera_refinement", "exposure") if (per_view := getattr(self, name)) is not None}
        apart = {id(p) for per_view in own.values() for p in per_view.parameters()}
        return [{"name": "field", "params": [p for p in self.parameters() if id(p) not in apart]},
                *({"name": name, "params": list(per_view.parameters()), "lr": per_view.lr} for name, per_view in own.items())]

    def on_fit_start(self) -> None:
        space = getattr(getattr(self.trainer, "datamodule", None), "space", None)
        if space is not None:
            self.use_space(space)
        if self.depth_loss and self.space.ndc is not None:
            raise ValueError("model.depth_loss > 0 compares distances along the world's rays, and data.ndc=true samples in NDC: "
                             "set model.depth_loss=0 or data.ndc=false")

    def render(self, rays_o: torch.Tensor, rays_d: torch.Tensor, perturb: bool = False, camera_indices: torch.Tensor | None = None) -> dict[str, Any]:
        """(N, 3) world rays with unit directions (and (N,) the training image of each, or None for other views) ->
        rgb (N, 3), depth (N,), accumulation (N,), and the renderer's ``weights`` and ``n_evaluated`` and the
        sampler's ``samples`` (see :class:`~nerf_lightning.rendering.renderer.Renderer`)."""
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
            for key in keys:  # only these: a chunk's samples and weights go with the next chunk (a whole frame's would not fit)
                parts[key].append(out[key])
        return {key: torch.cat(parts[key]) for key in keys}

    @torch.no_grad()
    def render_view(self, K: torch.Tensor, c2w: torch.Tensor, height: int, width: int,
                    abort: Callable[[], bool] | None = None) -> dict[str, torch.Tensor] | None:
        """One pinhole view (the model contract, :class:`~nerf_lightning.models.contract.RendersCamera`): K (3, 3) and
        an OpenCV c2w (4, 4) -> rgb (H, W, 3), depth (H, W), accumulation (H, W) on the model's device, rendered
        ``chunk_size`` rays at a time; None when ``abort()`` turns true between two chunks."""
        rays_o, rays_d = image_rays(K[None].to(self.device, torch.float32), c2w[None].to(self.device, torch.float32), height, width)
        out = self.render_chunked(rays_o[0], rays_d[0], abort=abort)
        if out is None:
            return None
        return {key: value.reshape(height, width, -1).squeeze(-1) for key, value in out.items()}

    # -- what it can do beyond rendering (the contract's capabilities) ------------------------------------------

    def density_at(self, points: torch.Tensor) -> torch.Tensor:
        """(N, 3) points in the sampling space -> (N,) the field's density there (differentiable in the points)."""
        return self.field.density(self.space.to_field(points))

    def colour_at(self, points: torch.Tensor, viewdirs: torch.Tensor) -> torch.Tensor:
        """(N, 3) points in the sampling space, seen along (N, 3) unit directions -> (N, 3) the field's colour."""
        return self.field(self.space.to_field(points), viewdirs)["rgb"]

    def _box(self) -> torch.Tensor | None:
        """(6,) the field's box, or its occupancy grid's; None without one."""
        for owner in (self.field, self.sampler.grid):
            if owner is not None and owner.aabb is not None:
                return owner.aabb
        return None

    def mesh_box(self) -> tuple[torch.Tensor, torch.Tensor]:
        """low, high (3,): the bounded part of the field's box in the sampling space
        (:meth:`SceneSpace.bounded_box <nerf_lightning.geometry.space.SceneSpace.bounded_box>`), else [-1.5, 1.5]^3."""
        aabb = self._box()
        return self.space.bounded_box(aabb if aabb is not None else torch.tensor([-1.5, -1.5, -1.5, 1.5, 1.5, 1.5]))

    def overlay_names(self) -> dict[str, str]:
        """What the viewer can draw: the scene's box (where the field has one) and an occupancy grid's occupied cells."""
        names = {}
        if self._box() is not None:
            names["box"] = "Scene box"
        if self.sampler.grid is not None:
            names["occupied_cells"] = "Occupied cells"
        return names

    def overlay(self, name: str) -> Overlay | None:
        """``box``: the world edges of the part of the box that has a place in the world (all of it for a bounded
        scene, the inner box of a contracted one, the box short of infinity in NDC); ``occupied_cells``: the world
        centres of the occupancy grid's occupied cells (at most 100 000, evenly thinned)."""
        if name == "box":
            aabb = self._box()
            if aabb is None:
                return None
            low, high = self.space.bounded_box(aabb)
            ndc = self.space.ndc
            edges = box_edges(low, high, (lambda p: p) if ndc is None else (lambda p: ndc.to_world(p.double())))
            return Overlay("Scene box", "lines", edges, (200, 40, 160), 2.0)
        if name == "occupied_cells":
            grid = self.sampler.grid
            if grid is None:
                return None
            centres, size = occupied_centres(grid, self.space)
            return Overlay("Occupied cells", "points", centres, (240, 120, 30), size) if len(centres) else None
        raise ValueError(f"{type(self).__name__} has no overlay '{name}': it has {', '.join(self.overlay_names()) or 'none'}")

    def training_step(self, batch: RayBatch, batch_idx: int) -> torch.Tensor:
        self.sampler.update(self.global_step, self.field)  # a grid refresh: outside the compiled graph, on its own steps
        if self.mask_loss:
            masks_for_mask_loss(batch)  # one line, outside the compiled graph, where the batch has no masks
        if self.depth_loss:
            depth_for_depth_loss(batch)  # the same for depth
        terms = self.step_losses(batch) if self.compiled_step is None else self.compiled_step(self, batch)
        loss = terms.pop("loss")
        # how many rays the sampler's samples a step would hold (RaySamples.rays_that_fit: models.ray_budget.RayBudget
        # sizes later steps by it), or None
        self.rays_that_fit = terms.get("rays_that_fit")
        self.log("train/samples_per_ray", terms.pop("samples_per_ray"), on_step=True)  # tensors: not read back here
        self.log("train/psnr", mse_to_psnr(terms.pop("mse")), on_step=True)
        for name, value in terms.items():
            self.log(f"train/{name}", value, on_step=True)
        self.log("train/loss", loss.detach(), on_step=True, on_epoch=False)
        # a size known on the host, logged as a device tensor made by a fill (a float would be copied to the device,
        # a copy that waits for it)
        self.log("train/rays", batch["rays_o"].new_full((), float(batch["rays_o"].shape[0])), on_step=True)
        return loss

    def step_losses(self, batch: RayBatch) -> dict[str, torch.Tensor]:
        """The training step's tensors, from a batch of N rays to the loss (what ``compile`` compiles): ``loss``
        (the one to minimise), ``mse`` and ``samples_per_ray`` (detached), each extra loss as ``loss_<name>``
        (the sampler's, the camera corrections' and the appearance embedding's penalties, detached) and, where the
        samples have it, ``rays_that_fit`` (0-d, :attr:`RaySamples.rays_that_fit
        <nerf_lightning.rendering.packed.RaySamples.rays_that_fit>`)."""
        rays_o, rays_d, camera_index = batch["rays_o"], batch["rays_d"], batch.get("camera_index")
        if self.camera_refinement is not None and camera_index is not None:
            rays_o, rays_d = self.camera_refinement(rays_o, rays_d, camera_index)
        out = self.render(rays_o, rays_d, perturb=True, camera_indices=camera_index)
        rgb, target = out["rgb"], batch["rgb"]
        if self.exposure is not None and camera_index is not None:  # each ray its photo's gains, the background as it is
            rgb = self.exposure(rgb, camera_index, out["accumulation"], self.space.background)
        if self.train_background == "random":  # what a ray leaves transparent shows a random colour, not the photo's
            colour = torch.rand_like(rgb)
            rgb = rgb + (1.0 - out["accumulation"])[:, None] * (colour - self.space.background.to(rgb))
            if "object_mask" in batch:  # data.masks=background: outside the object the target is that colour too
                target = composite_background(target, batch["object_mask"], colour)
        samples = out.get("samples")
        # (N,) the rays the sampler cut short stay out of the loss (None: it cut none)
        complete = samples.complete if samples is not None else None
        if complete is None:
            mse = F.mse_loss(rgb, target)
        else:
            mse = ((rgb - target).square().mean(dim=1) * complete).sum() / complete.sum().clamp(min=1)
        extra_losses = self.sampler.losses(out["samples"], out, target)
        mask_loss = self.mask_loss if self.mask_loss is not None else MASK_LOSS_WITH_MASKS * ("object_mask" in batch)
        if mask_loss:
            # a ray the sampler cut short has only part of its opacity: left out, as from the colours' loss
            extra_losses["mask"] = mask_loss * opacity_mask_loss(out["accumulation"], batch["object_mask"], complete)
        if self.depth_loss:  # as the colours' loss, without the rays the sampler cut short
            extra_losses["depth"] = self.depth_loss * depth_l1(out["depth"], batch["depth"], complete)
        if self.camera_refinement is not None:
            extra_losses.update(self.camera_refinement.penalties())
        appearance = self.field.appearance
        if appearance is not None:
            extra_losses.update(appearance.penalties())
        if self.exposure is not None:
            extra_losses.update({f"exposure_{name}": value for name, value in self.exposure.penalties().items()})
        loss = mse + sum(extra_losses.values())
        if not loss.requires_grad:  # no ray of the batch met an occupied cell: nothing to learn, but the step goes on
            loss = loss + sum(parameter.sum() for parameter in self.parameters()) * 0.0
        terms = {"loss": loss, "mse": mse.detach(), "samples_per_ray": out["n_evaluated"] / rays_o.shape[0]}
        terms.update({f"loss_{name}": value.detach() for name, value in extra_losses.items()})
        if samples is not None and samples.rays_that_fit is not None:
            terms["rays_that_fit"] = samples.rays_that_fit.detach()
        return terms

def box_edges(low: torch.Tensor, high: torch.Tensor, to_world: Callable[[torch.Tensor], torch.Tensor]) -> np.ndarray:
    """(12, 2, 3) float32 the edges of the box low..high (3,) mapped by ``to_world`` (lines stay lines: identity or NDC)."""
    corners = torch.tensor([[x, y, z] for x in (0, 1) for y in (0, 1) for z in (0, 1)], dtype=torch.float32)
    corners = to_world(low + corners * (high - low)).float()
    edges = [(a, b) for a in range(8) for b in range(a + 1, 8) if bin(a ^ b).count("1") == 1]
    return torch.stack([torch.stack([corners[a], corners[b]]) for a, b in edges]).numpy()


def occupied_centres(grid, space: SceneSpace, limit: int = 100_000) -> tuple[np.ndarray, float]:
    """(M, 3) float32 world centres of an occupancy grid's occupied cells (at most ``limit``, evenly thinned; for a
    contracted scene those of the inner box; in NDC those short of infinity) and the cell size."""
    centres = grid.cell_centres()[grid.binary].detach().float().cpu()  # (M, 3) field space
    if space.contraction is not None:
        centres = centres[(centres.abs() <= 1.0).all(dim=-1)]
    if space.ndc is not None:
        centres = centres[centres[:, 2] < space.ndc.mesh_far_z]
        centres = space.ndc.to_world(centres.double()).float()
    if centres.shape[0] > limit:
        centres = centres[torch.linspace(0, centres.shape[0] - 1, limit).long()]
    size = float((grid.aabb[3:] - grid.aabb[:3]).min()) / grid.resolution
    return centres.numpy(), size
