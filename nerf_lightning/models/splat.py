"""Fitting 3D Gaussians to posed images (3D Gaussian splatting, Kerbl et al. 2023), in plain PyTorch.

Each step draws one training view (or a patch: ``data=views``), projects the Gaussians into its camera
(:mod:`~nerf_lightning.splats.projection`), rasterises them (:mod:`~nerf_lightning.splats.draw`) and takes
the loss (``model.loss``, :class:`~nerf_lightning.splats.loss.SplatLoss`: 0.8 L1 + 0.2 (1 - SSIM)) against the photo;
a strategy (:mod:`~nerf_lightning.splats.strategy`) grows and prunes the Gaussians from the screen-space gradients.
Where the Gaussians start is an object of its own (``model/start``, :mod:`~nerf_lightning.models.splat_start`).
"""

from __future__ import annotations

import logging
import math
from collections.abc import Callable
from typing import Any

import torch
from torch.profiler import record_function

from nerf_lightning.data.batches import ViewBatch
from nerf_lightning.data.image_stack import as_float_rgb
from nerf_lightning.data.masks import composite_background
from nerf_lightning.data.views import ViewDataModule
from nerf_lightning.devices import memory_of
from nerf_lightning.geometry.cameras import pixel_ray_lengths
from nerf_lightning.geometry.refinement import CameraRefinement
from nerf_lightning.geometry.space import SceneSpace
from nerf_lightning.metrics import mse_to_psnr
from nerf_lightning.models.base import SceneModule
from nerf_lightning.models.splat_config import config_before_04
from nerf_lightning.models.splat_start import SparsePointsStart, Start
from nerf_lightning.parameters.exposure import ViewExposure
from nerf_lightning.parameters.per_view import PerViewTable
from nerf_lightning.splats.appearance import ViewColourAffine
from nerf_lightning.splats.gaussians import PARAMETERS, Gaussians
from nerf_lightning.splats.draw import Rasterizer, TileRasterizer, ViewDrawer, device_for_splats
from nerf_lightning.splats.loss import SplatLoss
from nerf_lightning.splats.projection import Projection
from nerf_lightning.splats.sh import coefficients_for
from nerf_lightning.splats.strategy import Strategy

log = logging.getLogger(__name__)


class SplatModule(SceneModule):
    """Trains Gaussian splats on whole training views or patches (``data=views``).

    Under the model contract it renders a camera (:meth:`render_view`); it has no density field to mesh.
    Logs ``train/loss`` every step, ``train/psnr`` and ``train/gaussians`` at the steps the logger writes and the
    last (and the per-view tables' penalties,
    ``train/loss_appearance`` and ``train/loss_camera_*``, where they are on; ``train/loss_mask`` and ``train/loss_depth``
    with their losses) and ``val/psnr``, ``val/ssim`` (and
    ``val/depth_error`` where the scene has true depth) over whole held-out views.

    Args:
        gaussians: the :class:`~nerf_lightning.splats.gaussians.Gaussians` (empty until fitting starts; their colours'
            degree goes up every ``gaussians.sh_degree_interval`` steps of training).
        optimizer: builds the optimiser (Adam, eps 1e-15) from the groups (a Hydra ``_partial_``).
        learning_rates: each parameter's learning rate (gsplat's): ``means`` (times the scene scale, decaying to
            ``means_final_ratio`` of it over ``steps``), ``log_scales``, ``quats``, ``opacity_logits``, ``sh0``, ``shN``.
        scheduler: a learning-rate scheduler over every group (a Hydra ``_partial_``), or None.
        strategy: densification (:class:`~nerf_lightning.splats.strategy.DefaultStrategy` or
            :class:`~nerf_lightning.splats.mcmc.MCMCStrategy`, whose regulariser joins the loss), or None.
        steps: the steps the means' learning rate decays over (the run's ``trainer.max_steps``).
        start: where the Gaussians start when fitting starts on a new run (``model/start``:
            :mod:`~nerf_lightning.models.splat_start`); None: the capture's sparse points, else a random box.
        rasterizer: what draws a view (:mod:`~nerf_lightning.splats.draw`, ``model/rasterizer``): the tile
            rasteriser of the device (:class:`~nerf_lightning.splats.draw.TileRasterizer`, None: that one) or plain
            PyTorch's pairs (:class:`~nerf_lightning.splats.draw.PairsRasterizer`), with the pairs' memory budget
            (``max_pairs``) and Mip-Splatting's opacity compensation of the low-pass filter (``antialiased``).
        loss: what a training step is scored by (:class:`~nerf_lightning.splats.loss.SplatLoss`: the SSIM's weight,
            the mask loss, the training background); None: its defaults.
        appearance: a learnt colour transform for each training view
            (:class:`~nerf_lightning.splats.appearance.ViewColourAffine`: the Gaussians' colours in a training view's
            render, not the background, through its affine map before the loss; its own learning rate, its penalty
            logged as ``train/loss_appearance``), or each photo's exposure and white balance alone
            (:class:`~nerf_lightning.parameters.exposure.ViewExposure`: three gains a photo); None: none. Held-out
            views are drawn without it (the training photos' mean).
        camera_refinement: learn a pose correction for each training view
            (:class:`~nerf_lightning.geometry.refinement.CameraRefinement`: the training view's c2w corrected before
            projecting; its own learning rate, its penalties logged as ``train/loss_camera_*``); None keeps the poses
            as loaded. Held-out views keep their loaded poses.
    """

    kind = "splats"
    # a checkpoint's model config of before 0.4 (the start's, the loss's keys at the top) read as this one's
    upgrade_config = staticmethod(config_before_04)

    def __init__(self, gaussians: Gaussians, optimizer: Callable[..., torch.optim.Optimizer], learning_rates: dict[str, float],
                 scheduler: Callable[..., Any] | None = None, strategy: Strategy | None = None, steps: int = 30_000,
                 means_final_ratio: float = 0.01, start: Start | None = None, rasterizer: Rasterizer | None = None,
                 loss: SplatLoss | None = None, appearance: ViewColourAffine | ViewExposure | None = None,
                 camera_refinement: CameraRefinement | None = None) -> None:
        super().__init__(optimizer, scheduler)
        missing = set(PARAMETERS) - set(learning_rates)
        if missing:
            raise ValueError(f"model.learning_rates needs a rate for {', '.join(sorted(missing))}")
        self.gaussians, self.strategy = gaussians, strategy
        self.learning_rates = dict(learning_rates)
        self.steps, self.means_final_ratio = steps, means_final_ratio
        self.start = SparsePointsStart() if start is None else start
        self.loss = SplatLoss() if loss is None else loss
        self.appearance, self.camera_refinement = appearance, camera_refinement
        self.rasterizer = TileRasterizer() if rasterizer is None else rasterizer
        self.register_buffer("scene_scale", torch.tensor(1.0))
        self._drawn: tuple[Projection, int, int, float] | None = None  # what the strategy reads after the backward pass
        self._step_logged: tuple[torch.Tensor, torch.Tensor, float | None] | None = None  # rgb, image, mse, until logged
        self.view_size: tuple[int, int] | None = None  # a whole training view's height and width (set by setup)

    # -- fitting starts: the scene's space, its scale and the Gaussians' start --------------------------------

    def setup(self, stage: str) -> None:
        datamodule = getattr(getattr(self, "trainer", None), "datamodule", None)
        if stage != "fit" or datamodule is None:
            return
        if not isinstance(datamodule, ViewDataModule):
            raise ValueError("Gaussian splats train on whole views or patches: use data=views (with data/scene=<format>), "
                             f"not the {type(datamodule).__name__}'s batches")
        space = datamodule.space  # the DataModule is set up before the model
        if space.ndc is not None or space.contraction is not None:
            raise ValueError("Gaussian splats live in the scene's own world: data.ndc and data.contract must be false for model=splat")
        self.use_space(space)
        for table in self.per_view_tables().values():  # sized before the optimiser is built and a checkpoint restored
            table.resize(len(datamodule.scene.train))
        self.view_size = (datamodule.scene.train.height, datamodule.scene.train.width)
        centres = datamodule.scene.train.c2w[:, :3, 3]
        self.scene_scale.fill_(1.1 * float((centres - centres.mean(dim=0)).norm(dim=-1).max()))
        if self.strategy is not None:
            self.strategy.scene_scale = float(self.scene_scale)
            train = datamodule.scene.train
            self.strategy.cameras = (train.K, train.c2w, train.height, train.width)
            if hasattr(self.strategy, "score_views"):  # a strategy that asks how the Gaussians draw in sampled views
                self.strategy.score_views = self.view_scores
        if len(self.gaussians) == 0 and not getattr(self.trainer, "ckpt_path", None):  # a resumed run's come from its checkpoint
            self.start(self.gaussians, datamodule.scene, getattr(datamodule, "mask_mode", None))
        self.check_memory(self.trainer.strategy.root_device)

    def check_memory(self, device: torch.device) -> None:
        """Refuse, before training, a Gaussian count whose parameters, gradients and Adam state would take more than
        half the device's memory (the rest is for the pairs, the images and the rest of the program)."""
        memory = memory_of(device)
        cap = getattr(self.strategy, "cap_max", None) or getattr(self.strategy, "max_count", None) or 0
        count, key = (cap, "model.strategy.max_count (or cap_max)") if cap > len(self.gaussians) else \
            (len(self.gaussians), "model.start.random.count (or the capture's sparse points)")
        per_gaussian = 16 * (3 + 4 + 3 + 1 + 3 * coefficients_for(self.gaussians.sh_degree))  # 4 float32 copies
        if memory is not None and count * per_gaussian > memory / 2:
            raise ValueError(f"{key} = {count} Gaussians would take about {count * per_gaussian / 2**30:.1f} GiB with their "
                             f"gradients and optimiser state, more than half of the {memory / 2**30:.1f} GiB the {device.type} "
                             f"has: lower it (or model.gaussians.sh_degree)")

    def use_space(self, space: SceneSpace) -> None:
        self.space = space.to(self.device)

    def parameter_groups(self) -> list[dict[str, Any]]:
        """One group a parameter at its own learning rate; the means' scaled by the scene and decaying exponentially."""
        rates, g = self.learning_rates, self.gaussians
        decay = self.means_final_ratio ** (1.0 / max(self.steps, 1))
        return [
            {"name": "means", "params": [g.means], "lr": rates["means"] * float(self.scene_scale), "schedule": lambda step: decay**step},
            *({"name": name, "params": [getattr(g, name)], "lr": rates[name]} for name in PARAMETERS if name != "means"),
            *({"name": name, "params": [table.rows], "lr": table.lr} for name, table in self.per_view_tables().items()),
        ]

    def per_view_tables(self) -> dict[str, PerViewTable]:
        """What is learnt a training view, by attribute name: ``appearance`` and ``camera_refinement``, those that are on."""
        return {name: table for name in ("appearance", "camera_refinement") if (table := getattr(self, name)) is not None}

    def on_load_checkpoint(self, checkpoint: dict[str, Any]) -> None:
        """A checkpoint without a per-view table this model has (trained before the tables, or without them) loads
        with the table as it is (no correction); resuming its run with the table is refused by name (its optimiser
        has no group for it)."""
        state = checkpoint.get("state_dict")
        missing = [name for name in self.per_view_tables() if state is not None and f"{name}.rows" not in state]
        if missing and self._trainer is not None and self._trainer.state.fn == "fit" and checkpoint.get("optimizer_states"):
            keys = ", ".join(f"model/{name}" for name in missing)
            raise ValueError(f"this checkpoint was trained without {keys}: a resumed run cannot add it (its optimiser has no group "
                             f"for it); resume without it, or start a new run with it")
        for name in missing:
            state[f"{name}.rows"] = getattr(self, name).rows.detach().clone()
        super().on_load_checkpoint(checkpoint)

    # -- drawing a camera ------------------------------------------------------------------------------------

    def sh_degree(self) -> int:
        """The colours' degree now: one more every ``gaussians.sh_degree_interval`` steps of training, all of it otherwise."""
        return self.gaussians.degree_at(self.global_step) if self.training else self.gaussians.sh_degree

    @staticmethod
    def device_for(device: torch.device | str, asked: bool) -> torch.device:
        """Where this model trains and draws when ``device`` was chosen (``asked``: by name, not ``auto``): the CPU's
        tiles in place of an Apple GPU not asked for (:func:`~nerf_lightning.splats.draw.device_for_splats`)."""
        return device_for_splats(device, asked)

    def drawer(self) -> ViewDrawer:
        """What draws a view on this model's device (``model.rasterizer``'s choice there): the projection and colours,
        the rasteriser, and the training loss that goes with them."""
        return self.rasterizer.for_device(self.device.type)

    def draw(self, K: torch.Tensor, c2w: torch.Tensor, height: int, width: int,
             background: torch.Tensor | None = None, depth: bool = True) -> tuple[dict[str, torch.Tensor], Projection]:
        """K (3, 3), OpenCV c2w (4, 4) -> rgb (H, W, 3), depth (H, W) (distance along the pixels' unit rays, as the
        NeRF renderers measure it; left out without ``depth``: a training step does not read it), accumulation
        (H, W), and the :class:`Projection` (for the strategy)."""
        K, c2w = K.to(self.device, torch.float32), c2w.to(self.device, torch.float32)
        drawer = self.drawer()
        projection, colours = drawer.project(self.gaussians, self.sh_degree(), K, c2w, height, width)
        background = self.space.background if background is None else background
        with record_function("splats.rasterize"):
            # the absolute screen-space gradients where the strategy reads them (AbsGS), in training only
            absgrad = self.training and self.strategy is not None and self.strategy.absgrad
            out = drawer.rasterize(projection, colours, height, width, background.to(colours), absgrad)
        if depth:
            out["depth"] = out["depth"] * pixel_ray_lengths(K, height, width)
        else:
            del out["depth"]
        return out, projection

    @torch.no_grad()
    def view_scores(self, views: torch.Tensor, error_threshold: float) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """Training views ``views`` (V,) -> for each Gaussian (N,) the mean over them of its blend weights on each
        view's high-error pixels (whose L1 error, the mean over the colours, exceeds ``error_threshold`` of the view's
        largest), (N,) the same on all their pixels, and (N,) bool whether any of them draws it at all.

        A Gaussian's blend weights summed over a set of pixels are the gradient, in its colour, of the rendered colours
        summed over them: each view is drawn once to find its errors, then once more with every colour 1 and
        backpropagated (the high-error pixels' sum through the red channel, every pixel's through the green). The
        views are drawn at their loaded poses, without the appearance transform, over the whole view (not
        ``data.masks=exclude``'s mask)."""
        train = self.trainer.datamodule.scene.train
        was_training = self.training
        self.eval()  # drawn as a held-out view is (no absgrad kept); the bands not yet reached are still zero
        try:
            return self._view_scores(train, views, error_threshold)
        finally:
            self.train(was_training)

    def _view_scores(self, train: Any, views: torch.Tensor, error_threshold: float) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        n = len(self.gaussians)
        high, drawn = torch.zeros(n, device=self.device), torch.zeros(n, device=self.device)
        seen = torch.zeros(n, dtype=torch.bool, device=self.device)
        for index in views.tolist():
            image = as_float_rgb(train.images[index]).to(self.device)
            out, projection = self.draw(train.K[index], train.c2w[index], train.height, train.width, depth=False)
            error = (out["rgb"] - image).abs().mean(dim=-1)
            errors = (error > error_threshold * error.max()).to(error.dtype)
            footprints = Projection(*(value.detach() for value in projection))
            with torch.enable_grad():
                ones = torch.ones(len(footprints.ids), 3, device=self.device, requires_grad=True)
                rgb = self.drawer().rasterize(footprints, ones, train.height, train.width,
                                              torch.zeros(3, device=self.device))["rgb"]
                ((rgb[..., 0] * errors).sum() + rgb[..., 1].sum()).backward()
            high.index_add_(0, footprints.ids, ones.grad[:, 0])
            drawn.index_add_(0, footprints.ids, ones.grad[:, 1])
            seen[footprints.ids] = True
        return high / len(views), drawn / len(views), seen

    @torch.no_grad()
    def render_view(self, K: torch.Tensor, c2w: torch.Tensor, height: int, width: int,
                    abort: Callable[[], bool] | None = None) -> dict[str, torch.Tensor] | None:
        """One pinhole view (the model contract): rgb (H, W, 3), depth (H, W), accumulation (H, W) on the model's device."""
        if abort is not None and abort():
            return None
        return self.draw(K, c2w, height, width)[0]

    def gaussian_parameters(self) -> dict[str, torch.Tensor]:
        """The Gaussians as 3DGS stores them (the contract's :class:`~nerf_lightning.models.contract.HasGaussians`):
        means (N, 3) in the scene's world, quats, log_scales, opacity_logits, sh0 (N, 1, 3), shN (N, K - 1, 3)."""
        return {name: getattr(self.gaussians, name).detach() for name in PARAMETERS}

    # -- training and validation ----------------------------------------------------------------------------------

    def training_step(self, batch: ViewBatch, batch_idx: int) -> torch.Tensor:
        image, c2w, camera_index = batch["image"], batch["c2w"], batch.get("camera_index")
        height, width = image.shape[:2]
        if self.camera_refinement is not None and camera_index is not None:
            c2w = self.camera_refinement.corrected_c2w(c2w[None].to(self.device, torch.float32), camera_index.reshape(1))[0]
        background = None  # the scene's
        if self.loss.train_background == "random":  # one colour a step, behind the Gaussians and outside the object
            background = torch.rand(3, device=image.device, dtype=image.dtype)
            if "object_mask" in batch:
                image = composite_background(image, batch["object_mask"], background)
        out, projection = self.draw(batch["K"], c2w, height, width, background=background, depth=self.loss.depth_loss > 0)
        if projection.means2d.requires_grad:
            projection.means2d.retain_grad()  # the strategy reads the screen-space gradient
        # the strategy reads gradients as of a whole view: a patch's loss, a mean over fewer pixels, gives each of its
        # Gaussians (whole view / patch) times the gradient the whole view would, and would grow far too many
        scale = int(batch.get("scale", 1))  # a coarse view (data.coarse_scale): whole, at its own size
        full_height, full_width = (self.view_size[0] // scale, self.view_size[1] // scale) if self.view_size else (height, width)
        self._drawn = (projection, full_width, full_height, height * width / (full_height * full_width))
        rgb = out["rgb"]
        if self.appearance is not None and camera_index is not None:  # the view's colour transform, the background as it is
            rgb = self.appearance(rgb, camera_index.reshape(()), out["accumulation"], self.space.background if background is None else background)
        mask = batch.get("loss_mask")  # data.masks=exclude: no gradient reaches a pixel outside; the loss a mean over the mask
        if mask is not None:
            rgb = torch.where(mask[..., None], rgb, image)
        with record_function("splats.loss"):
            loss, mse = self.loss.photometric(rgb, image, mask, fused=self.drawer().numba)
        if self.loss.mask_loss:
            mask_term = self.loss.of_mask(out["accumulation"], batch.get("object_mask"))
            loss = loss + mask_term
            self.log("train/loss_mask", mask_term.detach(), on_step=True, on_epoch=False)
        if self.loss.depth_loss:
            depth_term = self.loss.of_depth(out["depth"], batch.get("depth"), mask)
            loss = loss + depth_term
            self.log("train/loss_depth", depth_term.detach(), on_step=True, on_epoch=False)
        if not loss.requires_grad:  # the view saw no Gaussian: nothing to learn, but the step goes on
            loss = loss + sum(parameter.sum() for parameter in self.parameters()) * 0.0
        regulariser = None if self.strategy is None else self.strategy.loss(self.gaussians)  # MCMC's
        if regulariser is not None:
            loss = loss + regulariser
        for table in self.per_view_tables().values():
            for name, penalty in table.penalties().items():
                loss = loss + penalty
                self.log(f"train/loss_{name}", penalty.detach(), on_step=True, on_epoch=False)
        self.log("train/loss", loss, on_step=True, on_epoch=False)
        self._step_logged = (rgb.detach(), image, mse)
        if self.logs_this_step():  # what only the logger reads, made when it writes (each is a launch or more a step)
            self.log_step_figures()
        return loss

    def log_step_figures(self) -> None:
        """Log this step's ``train/psnr`` and ``train/gaussians`` (once a step)."""
        if self._step_logged is None:
            return
        rgb, image, mse = self._step_logged
        self._step_logged = None
        if mse is None:
            psnr = mse_to_psnr(torch.mean((rgb - image) ** 2))
        else:
            psnr = -10.0 * math.log10(mse) if mse > 0 else math.inf  # as mse_to_psnr has it
        self.log("train/psnr", psnr, on_step=True)
        self.log("train/gaussians", float(len(self.gaussians)), on_step=True)

    def on_after_backward(self) -> None:
        if self.strategy is not None and self._drawn is not None:
            projection, width, height, share = self._drawn
            if share != 1.0 and projection.means2d.grad is not None:
                projection.means2d.grad.mul_(share)
                absgrad = getattr(projection.means2d, "absgrad", None)
                if absgrad is not None:
                    absgrad.mul_(share)
            with record_function("splats.strategy"):
                self.strategy.after_backward(self.gaussians, projection, width, height)

    def on_train_batch_end(self, outputs: Any, batch: Any, batch_idx: int) -> None:
        self._drawn = None
        if self._trainer is not None and self.trainer.should_stop:  # stopped early (a time limit): the run's last figures
            self.log_step_figures()
        self._step_logged = None
        if self.strategy is not None:
            with record_function("splats.strategy"):
                self.strategy.after_step(self.gaussians, self.global_step, self.replace_parameter, self.means_lr())

    def means_lr(self) -> float:
        """The means' learning rate this step (their optimiser group's, as its schedule has it; before the optimiser is
        built, the configured rate times the scene scale): MCMC scales its noise by it."""
        for optimizer in (self._trainer.optimizers if self._trainer is not None else []):
            for group in optimizer.param_groups:
                if group.get("name") == "means":
                    return float(group["lr"])
        return self.learning_rates["means"] * float(self.scene_scale)
