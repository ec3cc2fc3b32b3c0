"""The live view while training (``nerf-train viewer=live``): a Lightning callback that serves the model in the
browser between training steps, through the viewer of ``nerf-view`` (:mod:`~nerf_lightning.viz.viewer`)."""

from __future__ import annotations

import logging
import time
from pathlib import Path
from typing import Any

import lightning as L
import torch

from nerf_lightning.models.contract import RendersCamera, implements

log = logging.getLogger(__name__)


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
