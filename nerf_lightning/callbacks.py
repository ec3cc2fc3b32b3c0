"""Lightning callbacks: snapshots of validation renders, PSNR history and curve, the run's config in checkpoints, a
progress bar counted in optimiser steps, the live view in the browser."""

from __future__ import annotations

import logging
import time
from datetime import timedelta
from pathlib import Path
from typing import Any

import imageio.v3 as iio
import lightning as L
import torch
from lightning.pytorch.callbacks import ModelCheckpoint
from lightning.pytorch.callbacks.progress.progress_bar import ProgressBar
from lightning.pytorch.loggers import TensorBoardLogger
from tqdm import tqdm

from nerf_lightning import __version__
from nerf_lightning.checkpoints import CHECKPOINT_FORMAT
from nerf_lightning.io import write_json, write_png
from nerf_lightning.models.contract import RendersCamera, implements
from nerf_lightning.plots import plot_psnr_curves
from nerf_lightning.video import write_gif

log = logging.getLogger(__name__)


class TrainingClock:
    """Seconds of training: since :meth:`start`, less the stretches between :meth:`pause` and :meth:`resume`
    (validations), plus ``before`` (the seconds of earlier sessions of a resumed run)."""

    def __init__(self) -> None:
        self.before = 0.0
        self._started: float | None = None
        self._paused: float | None = None

    @property
    def running(self) -> bool:
        return self._started is not None

    def start(self) -> None:
        self._started = time.perf_counter()

    def pause(self) -> None:
        self._paused = time.perf_counter()

    def resume(self) -> None:
        if self._paused is not None and self._started is not None:
            self._started += time.perf_counter() - self._paused
        self._paused = None

    def seconds(self) -> float:
        if self._started is None:
            return self.before
        now = time.perf_counter()
        paused = now - self._paused if self._paused is not None else 0.0
        return self.before + now - self._started - paused


class TimedCallback(L.Callback):
    """A callback with a :class:`TrainingClock` that runs with training and stops during validations."""

    def __init__(self) -> None:
        self.clock = TrainingClock()

    def on_train_start(self, trainer: L.Trainer, pl_module: L.LightningModule) -> None:
        self.clock.start()

    def on_validation_start(self, trainer: L.Trainer, pl_module: L.LightningModule) -> None:
        self.clock.pause()

    def on_validation_end(self, trainer: L.Trainer, pl_module: L.LightningModule) -> None:
        self.clock.resume()


class Snapshots(TimedCallback):
    """Saves what each validation renders and the run's PSNR curve.

    Every image a validation step returns under ``images`` (name -> (H, W, 3) or (H, W) in [0, 1]) is
    written to ``<output_dir>/snapshots/<name>_<view>_step<step>.png`` and to TensorBoard as ``val/<name>_<view>``
    (the ``target`` images once only). The history of ``train/psnr`` (every step) and ``val/psnr`` is
    written to ``psnr_history.json`` after each validation and plotted to ``psnr.png`` when training ends.
    The history is part of the callback's checkpoint state, so a resumed run keeps its whole curve.
    When training ends, the snapshots of the first view become ``montage.gif``: the fit over training.
    """

    def __init__(self, output_dir: str, dirname: str = "snapshots") -> None:
        self.output_dir = Path(output_dir)
        self.dirname = dirname
        self.history: dict[str, list[float]] = {
            "train_step": [], "train_psnr": [], "train_seconds": [], "val_step": [], "val_psnr": [], "val_seconds": []
        }
        self._targets_logged: set[int] = set()
        super().__init__()  # the clock: validation is not training time

    def on_train_batch_end(self, trainer: L.Trainer, pl_module: L.LightningModule, outputs: Any, batch: Any, batch_idx: int) -> None:
        # the PSNR the model logged from its photometric MSE, as TensorBoard shows it: not the total loss, which for
        # splats (L1 + D-SSIM) and the proposal presets (interlevel and distortion terms) is no MSE
        psnr = trainer.callback_metrics.get("train/psnr")
        if psnr is None or trainer.global_step % max(trainer.log_every_n_steps, 1) != 0:  # reading it waits on the device
            return
        self.history["train_step"].append(trainer.global_step)
        self.history["train_psnr"].append(float(psnr))
        self.history["train_seconds"].append(round(self.clock.seconds(), 4))

    def on_validation_batch_end(
        self, trainer: L.Trainer, pl_module: L.LightningModule, outputs: Any, batch: Any, batch_idx: int, dataloader_idx: int = 0
    ) -> None:
        if trainer.sanity_checking or not trainer.is_global_zero or not isinstance(outputs, dict):
            return
        step = trainer.global_step
        # Lightning logs this validation's scalars at step - 1 (the index of the batch just finished): match it
        tb_step = max(step - 1, 0)
        images = dict(outputs.get("images", {}))
        if "target" in images and "rgb" in images:
            # truth | render | depth, one picture to compare at a glance
            panels = [images["target"], images["rgb"]] + ([images["depth"][..., None].expand(-1, -1, 3)] if "depth" in images else [])
            side_by_side = torch.cat([panel.detach().float().cpu() for panel in panels], dim=1)
            for logger in trainer.loggers:
                if isinstance(logger, TensorBoardLogger):
                    logger.experiment.add_image(f"val/compare_{batch_idx:02d}", side_by_side.clamp(0, 1), tb_step, dataformats="HWC")
        for name, image in images.items():
            if name == "target":
                if batch_idx in self._targets_logged:
                    continue
                self._targets_logged.add(batch_idx)
            else:
                write_png(self.output_dir / self.dirname / f"{name}_{batch_idx:02d}_step{step:06d}.png", image)
            for logger in trainer.loggers:
                if isinstance(logger, TensorBoardLogger):
                    tb_image = image if image.ndim == 3 else image[..., None].expand(-1, -1, 3)
                    logger.experiment.add_image(f"val/{name}_{batch_idx:02d}", tb_image.clamp(0, 1).cpu(), tb_step, dataformats="HWC")

    def on_validation_epoch_end(self, trainer: L.Trainer, pl_module: L.LightningModule) -> None:
        if trainer.sanity_checking or "val/psnr" not in trainer.callback_metrics:
            return
        self.history["val_step"].append(trainer.global_step)
        self.history["val_psnr"].append(float(trainer.callback_metrics["val/psnr"]))
        # the validated weights are those after the last training step: its training clock, not the time since
        self.history["val_seconds"].append(self.history["train_seconds"][-1] if self.history["train_seconds"] else round(self.clock.seconds(), 4))
        if trainer.is_global_zero:
            write_json(self.output_dir / "psnr_history.json", self.history)

    def on_train_end(self, trainer: L.Trainer, pl_module: L.LightningModule) -> None:
        if not trainer.is_global_zero:
            return
        write_json(self.output_dir / "psnr_history.json", self.history)
        plot_psnr_curves(
            {
                "train (batch)": (self.history["train_step"], self.history["train_psnr"]),
                "val (whole image)": (self.history["val_step"], self.history["val_psnr"]),
            },
            self.output_dir / "psnr.png",
            title=f"PSNR over training: {self.output_dir.name}",
        )
        snapshots = sorted((self.output_dir / self.dirname).glob("rgb_00_step*.png"))
        if snapshots:
            write_gif(self.output_dir / "montage.gif", [iio.imread(path) for path in snapshots], fps=2.0)

    def state_dict(self) -> dict[str, Any]:
        return {"history": self.history, "training_seconds": self.clock.seconds()}

    def load_state_dict(self, state_dict: dict[str, Any]) -> None:
        self.history.update({key: list(values) for key, values in state_dict["history"].items()})
        self.clock.before = float(state_dict.get("training_seconds", 0.0))


class StepOrTimeCheckpoint(ModelCheckpoint):
    """Lightning's ModelCheckpoint saving every ``every_n_train_steps`` steps *or* every ``train_time_interval``
    seconds of training, whichever comes first (Lightning takes one or the other): a GPU makes many times a CPU's
    steps a second, so a time interval bounds the work a crash loses on both, and the step count keeps
    checkpoints at known steps where a test or a sweep needs them. Either may be None (off)."""

    def __init__(self, *args: Any, every_n_train_steps: int | None = None, train_time_interval: float | None = None, **kwargs: Any) -> None:
        super().__init__(*args, every_n_train_steps=every_n_train_steps, **kwargs)
        if train_time_interval is not None:
            if train_time_interval <= 0:
                raise ValueError(f"callbacks.last_checkpoint.train_time_interval must be a number of seconds > 0 or null, got {train_time_interval}")
            self._train_time_interval = timedelta(seconds=float(train_time_interval))


class RunConfigInCheckpoint(L.Callback):
    """Stores the run's resolved config and the model's kind in every checkpoint.

    ``nerf-render``, ``nerf-eval`` and ``nerf-export`` rebuild the model from this config, so a checkpoint
    is all they need.
    """

    def __init__(self, config: dict[str, Any]) -> None:
        self.config = config

    def on_save_checkpoint(self, trainer: L.Trainer, pl_module: L.LightningModule, checkpoint: dict[str, Any]) -> None:
        checkpoint["nerf_lightning"] = {
            "kind": getattr(pl_module, "kind", type(pl_module).__name__), "config": self.config, "format": CHECKPOINT_FORMAT, "version": __version__,
        }


class StepProgressBar(ProgressBar):
    """One bar over the run's optimiser steps, with steps a second, the current training PSNR and the last
    validation PSNR (Lightning's own bar counts "epochs", which here are the stretches between validations).
    ``nerf-train`` uses it wherever ``trainer.enable_progress_bar`` is true."""

    def __init__(self) -> None:
        super().__init__()
        self._enabled = True
        self.bar: tqdm | None = None

    def disable(self) -> None:
        self._enabled = False

    def enable(self) -> None:
        self._enabled = True

    @property
    def is_enabled(self) -> bool:
        return self._enabled

    def on_train_start(self, trainer: L.Trainer, pl_module: L.LightningModule) -> None:
        if self.is_enabled and trainer.is_global_zero:
            total = trainer.max_steps if trainer.max_steps and trainer.max_steps > 0 else None
            self.bar = tqdm(total=total, initial=trainer.global_step, unit="step", desc="training", dynamic_ncols=True, smoothing=0.05)

    def on_train_batch_end(self, trainer: L.Trainer, pl_module: L.LightningModule, outputs: Any, batch: Any, batch_idx: int) -> None:
        if self.bar is None:
            return
        self.bar.update(trainer.global_step - self.bar.n)
        if trainer.global_step % max(trainer.log_every_n_steps, 1) == 0:  # reading the metrics waits on the device
            self._show_psnr(trainer, refresh=False)

    def _show_psnr(self, trainer: L.Trainer, refresh: bool) -> None:
        # the logged tensors, read here and only here: a metric logged with prog_bar=True would be read back by
        # Lightning after every step (a wait for the device each step)
        shown = {key.replace("/", " "): f"{float(value):.2f}" for key, value in trainer.callback_metrics.items()
                 if key in ("train/psnr", "val/psnr")}
        self.bar.set_postfix(shown, refresh=refresh)

    def on_validation_start(self, trainer: L.Trainer, pl_module: L.LightningModule) -> None:
        if self.bar is not None:
            self.bar.set_description_str("validating", refresh=True)

    def on_validation_end(self, trainer: L.Trainer, pl_module: L.LightningModule) -> None:
        if self.bar is not None:
            self.bar.set_description_str("training", refresh=False)
            self._show_psnr(trainer, refresh=True)  # the new validation PSNR (validation has waited for the device already)

    def _close(self) -> None:
        if self.bar is not None:
            self.bar.close()
            self.bar = None

    def on_train_end(self, trainer: L.Trainer, pl_module: L.LightningModule) -> None:
        self._close()

    def on_exception(self, trainer: L.Trainer, pl_module: L.LightningModule, exception: BaseException) -> None:
        self._close()


def history_psnr(history: dict[str, list[float]]) -> tuple[list[float], list[float]]:
    """The validation curve of a ``psnr_history.json``, falling back to the training curve."""
    if history.get("val_step"):
        return history["val_step"], history["val_psnr"]
    return history.get("train_step", []), history.get("train_psnr", [])


__all__ = ["RunConfigInCheckpoint", "Snapshots", "StepProgressBar", "history_psnr"]


class LiveViewer(L.Callback):
    """nerf-train ``viewer=live``: the model in the browser while it trains, rendered between training steps
    (:class:`~nerf_lightning.viz.viewer.FieldViewer`; viser, extra ``viz``).

    Rendering takes at most ``time_share`` of the time since training started (a frame is skipped while the share is
    spent); frames are refined only up to what ``max_frame_s`` renders, and a camera that stays still is rendered
    again every ``refresh_s`` seconds, since the model changes; the overlays shown are drawn again every
    ``5 * refresh_s`` seconds. Frames are rendered without gradients, the module left in training mode (nothing of a
    render may outlive the step: the proposal sampler does not bake while the module trains). A browser that leaves
    costs nothing; an error in the viewer is logged once and training goes on without it.

    A model of Gaussians is drawn by the browser as splats (:mod:`nerf_lightning.viz.splats`) instead of frames (unless
    the page asks for rendered frames): they are sent again every ``splats_every_s`` seconds of wall time, so that
    the user watches them move and grow. Wall time, not steps: a step takes milliseconds on a small scene and a
    second on a large one, while what a refresh costs (up to 32 MB a million Gaussians through the socket, and the
    browser's sort) and what the eye follows are a matter of seconds; densification changes the count every few
    hundred steps, a few seconds apart at the usual speeds. Nothing is read or sent while no browser is connected,
    while the page shows rendered frames, or when no step was taken since the last refresh; and a refresh counts
    into ``time_share`` as a frame does.

    Args:
        host, port: where the page is served; checked when the callback is made, before any data is loaded.
        output_dir: the run's folder; the page's Render button writes GIFs to ``<output_dir>/renders/``.
        splats_every_s: a model of Gaussians: its splats are sent again every so many seconds.
    """

    def __init__(self, host: str = "127.0.0.1", port: int = 8080, output_dir: str | Path = ".", time_share: float = 0.1,
                 moving_frame_s: float = 0.1, max_resolution: int = 512, max_frame_s: float = 1.0, refresh_s: float = 2.0,
                 splats_every_s: float = 3.0) -> None:
        # imported here: viser is an optional extra, and only this callback needs it
        from nerf_lightning.viz.viser_view import check_port, require_viser

        if not 0.0 < time_share < 1.0:
            raise ValueError(f"callbacks.viewer.time_share must lie between 0 and 1, got {time_share}")
        require_viser()
        check_port(host, port, "callbacks.viewer.port")
        self.host, self.port, self.output_dir, self.time_share = host, int(port), Path(output_dir), float(time_share)
        self.options = dict(moving_frame_s=moving_frame_s, max_resolution=max_resolution, max_frame_s=max_frame_s, refresh_s=refresh_s)
        self.overlays_every_s = 5.0 * refresh_s
        self.splats_every_s = float(splats_every_s)
        self.viewer = None
        self.server = None
        self.rendering_seconds = 0.0
        self._started: float | None = None
        self._overlays_drawn_at = 0.0
        self._splats_refreshed_at = 0.0

    def setup(self, trainer: L.Trainer, pl_module: L.LightningModule, stage: str) -> None:
        if not implements(pl_module, RendersCamera):
            raise ValueError(f"viewer=live shows a model that renders a camera; this run trains a {type(pl_module).__name__}, "
                             "which renders none: leave viewer out, or train a radiance field (experiment=fast, ...)")
        if stage != "fit" or not trainer.is_global_zero or self.server is not None:
            return
        from nerf_lightning.viz.viewer import FieldViewer
        from nerf_lightning.viz.viser_view import start_server

        self.server = start_server(self.host, self.port, "callbacks.viewer.")
        datamodule = trainer.datamodule
        datamodule.setup("fit")
        self.viewer = FieldViewer(self.server, pl_module, datamodule.scene.train, datamodule.render_views,
                                  self.output_dir / "renders", **self.options)
        log.info("live view of the training field at http://%s:%d", self.host, self.port)

    def on_train_start(self, trainer: L.Trainer, pl_module: L.LightningModule) -> None:
        self._started = time.perf_counter()

    def on_train_batch_end(self, trainer: L.Trainer, pl_module: L.LightningModule, outputs: Any, batch: Any, batch_idx: int) -> None:
        if self.viewer is None or self._started is None:
            return
        elapsed = time.perf_counter() - self._started
        if self.rendering_seconds > self.time_share * elapsed:
            return
        if not self.server.get_clients() and not self.viewer.path_requested:
            return
        started = time.perf_counter()
        try:
            with torch.no_grad():
                if time.monotonic() - self._overlays_drawn_at > self.overlays_every_s:
                    self.viewer.page.redraw_overlays()  # an occupancy grid changes as the field trains
                    self._overlays_drawn_at = time.monotonic()
                if getattr(self.viewer, "has_gaussians", False) and time.monotonic() - self._splats_refreshed_at > self.splats_every_s:
                    self.viewer.refresh_splats(trainer.global_step)  # sent by render_next, if the page draws splats
                    self._splats_refreshed_at = time.monotonic()
                self.viewer.render_next()
            psnr = trainer.callback_metrics.get("train/psnr")
            splats = f"; {self.viewer.splats_shown:,} Gaussians drawn by the browser" if getattr(self.viewer, "splats_sent", 0) else ""
            self.viewer.show_training(f"training: step {trainer.global_step}" + ("" if psnr is None else f", train PSNR {float(psnr):.2f} dB")
                                      + f"; {self.viewer.frames_rendered} frames rendered" + splats)
        except Exception as error:  # the view is a convenience: training never stops for it
            log.warning("the live viewer stopped (%s: %s); training goes on without it", type(error).__name__, error)
            self.close()
        finally:
            self.rendering_seconds += time.perf_counter() - started

    def close(self) -> None:
        if self.viewer is not None and self._started is not None:
            elapsed = max(time.perf_counter() - self._started, 1e-9)
            log.info("live viewer: %d frames, %.1f s of rendering, %.1f%% of training", self.viewer.frames_rendered,
                     self.rendering_seconds, 100.0 * self.rendering_seconds / elapsed)
        if self.server is not None:
            try:
                self.server.stop()
            except Exception:  # stopping a server that failed: nothing more to report
                pass
        self.viewer, self.server = None, None

    def teardown(self, trainer: L.Trainer, pl_module: L.LightningModule, stage: str) -> None:
        self.close()

    def on_exception(self, trainer: L.Trainer, pl_module: L.LightningModule, exception: BaseException) -> None:
        self.close()


class RayBudget(L.Callback):
    """Instant-NGP's sample budget: the rays of the next training steps sized so that their samples fill the
    sampler's fixed capacity, from what the rays of an earlier step wanted, read back a step late so that the
    device never waits for the host.

    After each step the model's ``rays_that_fit`` (a 0-d device tensor from an occupancy grid of fixed capacity:
    how many rays of the samples a ray wanted its buffers would hold) is copied to the host without waiting (pinned
    memory and a CUDA event); at the start of a later step, once the copy has landed, ``data.batch_size`` becomes
    ``fill`` times it, rounded down to a multiple of ``multiple`` (so that a compiled step sees few sizes) and kept
    within ``min_rays``..``max_rays``. Too many rays and the last are cut short (left out of the loss); too few and
    the capacity is padding. The ray count is kept in checkpoints, so a resumed run goes on with it.

    Args:
        fill: the share of the capacity to aim at: below 1, a step whose rays want more than the last's still fits.
        min_rays, max_rays, multiple: the bounds of the ray count, and its step. The march's table of steps is
            (rays, reach / step size): ``max_rays`` bounds its memory (65 536 rays of 1040 steps: a few GB).

    On a GPU the step at which a count lands depends on timing, so two runs with a budget are not the same step for
    step (their quality is).
    """

    def __init__(self, fill: float = 0.9, min_rays: int = 1024, max_rays: int = 65_536, multiple: int = 1024) -> None:
        if not 0 < fill <= 1 or multiple < 1 or not multiple <= min_rays <= max_rays:
            raise ValueError(f"callbacks.ray_budget: expected 0 < fill <= 1 and multiple <= min_rays <= max_rays, got fill={fill}, "
                             f"multiple={multiple}, min_rays={min_rays}, max_rays={max_rays}")
        self.fill, self.min_rays, self.max_rays, self.multiple = fill, min_rays, max_rays, multiple
        self.rays: int | None = None
        self.pending: tuple[torch.Tensor, Any] | None = None

    def setup(self, trainer: L.Trainer, pl_module: L.LightningModule, stage: str) -> None:
        if stage != "fit":
            return
        if getattr(getattr(pl_module, "sampler", None), "capacity", None) is None:
            raise ValueError("callbacks.ray_budget sizes the rays a step to an occupancy grid's model.sampler.capacity, and this "
                             "model has none: set one (as experiment=fast_blender_gpu does), or remove the callback")
        pl_module.ray_count_varies = True  # a compiled step then traces one graph for any ray count

    def on_fit_start(self, trainer: L.Trainer, pl_module: L.LightningModule) -> None:
        # resumed: the ray count it had (the callback's state is restored before this hook, and the first batch is
        # drawn after it)
        if self.rays is not None:  # within this run's bounds, which may have changed (a lower max_rays after running out of memory)
            self.rays = self._bounded(self.rays)
            trainer.datamodule.batch_size = self.rays

    def on_train_batch_end(self, trainer: L.Trainer, pl_module: L.LightningModule, outputs: Any, batch: Any, batch_idx: int) -> None:
        fit = getattr(pl_module, "rays_that_fit", None)
        if fit is None or self.pending is not None:
            return
        if fit.device.type == "cuda":  # copied as the device gets there; read once the event says it has
            host = torch.empty((), dtype=fit.dtype, pin_memory=True)
            host.copy_(fit, non_blocking=True)
            event = torch.cuda.Event()
            event.record()
            self.pending = (host, event)
        else:  # a CPU, or a device without events (Apple's): in order with the host
            self.pending = (fit.detach().to("cpu", copy=True), None)

    def on_train_batch_start(self, trainer: L.Trainer, pl_module: L.LightningModule, batch: Any, batch_idx: int) -> None:
        if self.pending is None:
            return
        host, event = self.pending
        if event is not None and not event.query():
            return  # not there yet: a later step looks again
        self.pending = None
        self.rays = self._bounded(int(self.fill * float(host.numpy())))  # the host's copy: no device op
        trainer.datamodule.batch_size = self.rays  # the batches drawn from now on (the next may be drawn already)

    def _bounded(self, rays: int) -> int:
        """``rays`` rounded down to a multiple of ``multiple`` and kept within ``min_rays``..``max_rays``."""
        return min(max(rays // self.multiple * self.multiple, self.min_rays), self.max_rays)

    def state_dict(self) -> dict[str, Any]:
        return {"rays": self.rays}

    def load_state_dict(self, state_dict: dict[str, Any]) -> None:
        self.rays = state_dict.get("rays")
