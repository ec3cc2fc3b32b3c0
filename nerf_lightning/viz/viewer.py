"""A trained or training model of a scene in the browser: nerf-view, and nerf-train's live view (viser, extra ``viz``).

A :class:`FieldViewer` composes the :class:`~nerf_lightning.viz.page.ViewerPage` (the scene and controls) and a
:class:`~nerf_lightning.viz.scheduler.RenderScheduler` (which browser's camera to render next, and how large), and
renders each frame through the model's one method, ``model.render_view``
(:class:`~nerf_lightning.models.contract.RendersCamera`), stopping it when the camera moves on.

Rendering happens in one thread, one frame a call of :meth:`FieldViewer.render_next`: nerf-view loops on it
(:meth:`FieldViewer.serve_forever`); during training :class:`~nerf_lightning.viz.live.LiveViewer` calls it between
steps, within a share of the training time, so that the model is never rendered while the optimiser changes it.

A model of Gaussians (:class:`~nerf_lightning.models.contract.HasGaussians`) is drawn by the browser itself, as splats
(:mod:`nerf_lightning.viz.splats`: degree-0 colours, at most :data:`~nerf_lightning.viz.splats.MAX_SPLATS`), and no
frame is rendered for it, unless the page's "Drawn by" asks for rendered frames (every colour band, depth). The splats
are sent from the same thread as the frames (:meth:`FieldViewer.render_next`), once, and again after each
:meth:`FieldViewer.refresh_splats` (the live view, as the Gaussians train).
"""

from __future__ import annotations

import logging
import threading
import time
from collections.abc import Callable
from datetime import datetime
from pathlib import Path

import numpy as np
import torch

from nerf_lightning.data.scene import Views
from nerf_lightning.io import to_uint8
from nerf_lightning.outputs.frames import depth_picture, write_path_renders
from nerf_lightning.viz.page import OUTPUTS, ViewerPage
from nerf_lightning.viz.scheduler import BrowserCamera, RenderScheduler
from nerf_lightning.viz.splats import MAX_SPLATS, splat_arrays

log = logging.getLogger(__name__)


def frame_picture(model, frame: dict[str, torch.Tensor], output: str) -> np.ndarray:
    """(H, W, 3) uint8 of a rendered frame: its ``rgb``, its ``depth`` as ``model.space`` pictures it through the
    turbo colormap (near red, far blue, black where nothing is hit), or its ``accumulation`` in grey."""
    frame = {key: value.detach().cpu() for key, value in frame.items()}
    if output == "rgb":
        return to_uint8(frame["rgb"])
    if output == "depth":
        return to_uint8(depth_picture(model.space, frame["depth"], frame["accumulation"], "turbo"))
    if output == "accumulation":
        return np.repeat(to_uint8(frame["accumulation"])[..., None], 3, axis=-1)
    raise ValueError(f"the viewer shows {', '.join(OUTPUTS)}, not '{output}'")


class FieldViewer:
    """Serves a model of a scene to the browsers connected to a viser ``server`` (see the module's docstring).

    Args:
        server: a ``viser.ViserServer``.
        model: a :class:`~nerf_lightning.models.contract.RendersCamera` (and, for overlays, ``ShowsOverlays``; for
            splats drawn by the browser, ``HasGaussians``).
        train_views: the training cameras and images, drawn as frustums; where the view starts.
        render_views: ``(path, frames) -> Views``, the cameras of a render path (a DataModule's ``render_views``).
        output_dir: the button's GIFs go to ``<output_dir>/<time>_<path>/`` (as nerf-render writes them), the camera
            paths framed in the page to ``<output_dir>/camera_paths/``.
        moving_frame_s, max_resolution, max_frame_s, refresh_s: how frames are sized and refreshed
            (:class:`~nerf_lightning.viz.scheduler.RenderScheduler`).
        max_splats: the most Gaussians sent to the browser (the most opaque).
    """

    def __init__(self, server, model, train_views: Views, render_views: Callable[[str, int], Views], output_dir: str | Path,
                 moving_frame_s: float = 0.25, max_resolution: int = 512, max_frame_s: float | None = None,
                 refresh_s: float | None = None, max_splats: int = MAX_SPLATS) -> None:
        self.server, self.model, self.render_views = server, model, render_views
        self.output_dir = Path(output_dir)
        self.max_splats = int(max_splats)
        self.scheduler = RenderScheduler(moving_frame_s, max_resolution, max_frame_s, refresh_s)
        self.page = ViewerPage(server, model, train_views, render_views, max_resolution,
                               on_view_changed=self._view_changed, on_render_path=self._request_path,
                               on_drawn_by_changed=self._drawn_by_changed, camera_paths_dir=self.output_dir / "camera_paths")
        self.splats_sent = 0  # how many times the Gaussians were sent to the browsers
        self.splats_shown = 0  # how many Gaussians the browsers were last sent
        # the model's state the splats should show (refresh_splats) and the one they show: sent when they differ
        self._splats_wanted: object = 0
        self._splats_drawn: object = None
        self._splats_capped_logged = False
        self.last_frame: dict[int, dict] = {}  # client id -> {"picture", "height", "width", "output", "seconds"}
        self._path_request: tuple[str, int, float] | None = None
        self._stop = threading.Event()
        server.on_client_connect(self._connect)
        server.on_client_disconnect(self._disconnect)

    @property
    def frames_rendered(self) -> int:
        return self.scheduler.frames_rendered

    @property
    def path_requested(self) -> bool:
        """The page's Render button was pressed and that path is not rendered yet."""
        return self._path_request is not None

    def show_training(self, text: str) -> None:
        """The page's line on training (the live view)."""
        self.page.training.content = text

    # -- what the page reports ----------------------------------------------------------------------------------

    def _connect(self, client) -> None:
        self.scheduler.connect(client.client_id)
        client.camera.on_update(self._camera_moved)

    def _disconnect(self, client) -> None:
        self.scheduler.disconnect(client.client_id)
        self.last_frame.pop(client.client_id, None)

    def _camera_moved(self, camera) -> None:
        self.scheduler.camera_moved(camera.client.client_id, BrowserCamera(
            camera.wxyz.copy(), camera.position.copy(), float(camera.fov), float(camera.aspect), int(camera.image_height)))

    def _drawn_by_changed(self) -> None:
        """The page's "Drawn by" changed (its own thread: nothing of the model is read here)."""
        if self.page.splats_drawn:  # the browser draws the splats: no rendered frame behind them
            for client in self.server.get_clients().values():
                client.scene.set_background_image(None)
        else:
            self.scheduler.invalidate()

    def _view_changed(self) -> None:
        self.scheduler.max_resolution = max(8, int(self.page.max_resolution.value))
        self.scheduler.invalidate()

    def _request_path(self, path: str, frames: int, scale: float) -> None:
        self._path_request = (path, frames, scale)

    # -- rendering -----------------------------------------------------------------------------------------------

    @property
    def has_gaussians(self) -> bool:
        """A model of Gaussians (the page's "Drawn by" is shown for it)."""
        return self.page.has_gaussians

    @property
    def splats_due(self) -> bool:
        """The browser draws the splats, and they are older than the model (or not sent yet)."""
        return self.page.splats_drawn and self._splats_drawn != self._splats_wanted

    def refresh_splats(self, stamp: object) -> None:
        """The model is now as of ``stamp`` (the live view: the training step): the splats are sent again at the next
        :meth:`render_next` unless they already show that ``stamp``, or while the page shows rendered frames (then when
        it shows the splats again). Costs nothing itself."""
        self._splats_wanted = stamp

    def send_splats(self) -> float:
        """Send the model's Gaussians to the browsers now (reads the model: the rendering thread). Returns the seconds."""
        started = time.perf_counter()
        wanted = self._splats_wanted
        arrays = splat_arrays(self.model, self.max_splats)
        self.page.draw_splats(arrays)
        self._splats_drawn, self.splats_sent, self.splats_shown = wanted, self.splats_sent + 1, arrays.shown
        capped = arrays.shown < arrays.total
        if self.splats_sent == 1 or (capped and not self._splats_capped_logged):
            log.info("viewer: %s", arrays.describe())
            self._splats_capped_logged = capped
        return time.perf_counter() - started

    def render_next(self) -> float | None:
        """Do what is most wanted: a path requested by the button, else, for a model of Gaussians drawn by the
        browser, its splats when they are due (nothing otherwise), else one frame for one browser. Returns the
        seconds it took, or None when nothing was wanted."""
        if self._path_request is not None:
            started = time.perf_counter()
            self._render_path(*self._path_request)
            self._path_request = None
            return time.perf_counter() - started
        if self.page.splats_drawn:  # (a model of Gaussians only)
            return self.send_splats() if self.splats_due else None
        job = self.scheduler.next_job()
        if job is None:
            return None
        K, c2w, height, width = job.pinhole()
        started = time.perf_counter()
        frame = self.model.render_view(K, c2w, height, width, abort=lambda: self.scheduler.is_stale(job))
        output = self.page.output.value
        # timed up to the picture: its copy to the CPU waits for the device's render to finish
        picture = None if frame is None else frame_picture(self.model, frame, output)
        seconds = time.perf_counter() - started
        if frame is None or self.page.splats_drawn:  # the camera moved, the browser left or draws the splats now
            return seconds
        self.scheduler.rendered(job, width, seconds)
        client = self.server.get_clients().get(job.client_id)
        if client is None:
            return seconds
        client.scene.set_background_image(picture, format="jpeg", jpeg_quality=90)
        self.last_frame[job.client_id] = {"picture": picture, "height": height, "width": width, "output": output, "seconds": seconds}
        self.page.stats.content = (f"{output} {width}x{height} in {seconds:.2f} s (step {job.step} of {job.steps}), "
                                   f"{self.scheduler.rays_per_second / 1000:.0f}k rays/s")
        return seconds

    def _render_path(self, path: str, frames: int, scale: float) -> None:
        try:
            views = self.render_views(path, frames).scaled(scale)
            folder = self.output_dir / f"{datetime.now():%Y-%m-%d_%H-%M-%S}_{path}"
            write_path_renders(self.model, views, folder, desc=f"{path} path")
        except Exception as error:  # a wrong choice in the page is reported there; the viewer goes on
            log.warning("rendering the %s path failed: %s", path, error)
            self.page.path_status.content = f"the {path} path failed: {error}"
            return
        log.info("wrote %d %dx%d frames of the %s path to %s", len(views), views.width, views.height, path, folder)
        self.page.path_status.content = f"wrote {folder / 'rgb.gif'}"

    def serve_forever(self, idle_s: float = 0.01) -> None:
        """Render whatever the browsers want until :meth:`stop` (nerf-view's loop; Ctrl-C ends it too)."""
        while not self._stop.is_set():
            if self.render_next() is None:
                time.sleep(idle_s)

    def stop(self) -> None:
        self._stop.set()
