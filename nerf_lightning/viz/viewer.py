"""A trained or training radiance field in the browser: nerf-view, and nerf-train's ``viewer=true`` (viser, extra ``viz``).

A :class:`FieldViewer` renders the field from each browser's camera, progressively: while the camera moves, at the
size that the measured rays per second render within ``moving_frame_s``; once it stops, again at twice that height,
and twice again, up to ``max_resolution`` pixels high (:func:`progressive_heights`). A refinement is dropped as soon
as the camera moves again. The page shows rgb, depth or accumulation; the training cameras as frustums showing their
images (click one to look through it); the render path, with a button that renders it to GIFs as nerf-render does;
the scene's box and the occupancy grid's occupied cells as toggles.

Rendering happens in one thread, one frame a call of :meth:`FieldViewer.render_next`: nerf-view loops on it
(:meth:`FieldViewer.serve_forever`); during training :class:`LiveViewer` calls it between steps, within a share of
the training time, so that the field is never rendered while the optimiser changes it.
"""

from __future__ import annotations

import logging
import math
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass
from datetime import datetime
from pathlib import Path

import kornia
import numpy as np
import torch
from lightning.pytorch.callbacks import Callback

from nerf_lightning.data.scene import Views
from nerf_lightning.io import to_uint8
from nerf_lightning.rendering.views import depth_picture, render_view, write_path_renders
from nerf_lightning.viz.viser_view import add_training_cameras, check_port, require_viser, scene_frame, start_server

log = logging.getLogger(__name__)

OUTPUTS = ("rgb", "depth", "accumulation")
PATHS = ("orbit", "spiral", "test")


# -- pieces that need no browser -------------------------------------------------------------------------------


def progressive_heights(rays_per_second: float, moving_frame_s: float, aspect: float, max_height: int, min_height: int = 24) -> list[int]:
    """Image heights, in pixels, of the progressive renders of one camera position: the first renders within
    ``moving_frame_s`` at ``rays_per_second`` for an image ``aspect`` (width / height) wide (at least ``min_height``),
    each next one twice as high, the last ``max_height``."""
    first = int(math.sqrt(max(rays_per_second * moving_frame_s, 1.0) / aspect))
    heights = [max(min(first, max_height), min(min_height, max_height))]
    while heights[-1] * 2 < max_height:
        heights.append(heights[-1] * 2)
    if heights[-1] < max_height:
        if max_height < 1.25 * heights[-1] and len(heights) > 1:
            heights[-1] = max_height  # no step of a few pixels at the end
        else:
            heights.append(max_height)
    return heights


def browser_camera(wxyz: np.ndarray, position: np.ndarray, fov_y: float, aspect: float, height: int) -> tuple[torch.Tensor, torch.Tensor, int, int]:
    """A viser client camera (orientation ``wxyz`` and ``position`` of an OpenCV camera in the world, vertical field of
    view ``fov_y`` in radians, ``aspect`` width / height) at ``height`` pixels -> K (3, 3), c2w (4, 4), height, width."""
    width = max(1, round(height * aspect))
    focal = 0.5 * height / math.tan(0.5 * fov_y)
    K = torch.tensor([[focal, 0.0, 0.5 * width], [0.0, focal, 0.5 * height], [0.0, 0.0, 1.0]])
    c2w = torch.eye(4)
    quaternion = torch.as_tensor(np.asarray(wxyz, dtype=np.float64)).float()
    c2w[:3, :3] = kornia.geometry.conversions.quaternion_to_rotation_matrix(quaternion / quaternion.norm())
    c2w[:3, 3] = torch.as_tensor(np.asarray(position, dtype=np.float64)).float()
    return K, c2w, height, width


def frame_picture(model, frame: dict[str, torch.Tensor], output: str) -> np.ndarray:
    """(H, W, 3) uint8 of a rendered frame: its ``rgb``, its ``depth`` through the turbo colormap (near red, far blue,
    black where nothing is hit), or its ``accumulation`` in grey."""
    if output == "rgb":
        return to_uint8(frame["rgb"])
    if output == "depth":
        return to_uint8(depth_picture(model, frame["depth"], frame["accumulation"], "turbo"))
    if output == "accumulation":
        return np.repeat(to_uint8(frame["accumulation"])[..., None], 3, axis=-1)
    raise ValueError(f"the viewer shows {', '.join(OUTPUTS)}, not '{output}'")


def _box_edges(low: torch.Tensor, high: torch.Tensor, to_world: Callable[[torch.Tensor], torch.Tensor]) -> np.ndarray:
    """(12, 2, 3) the edges of the box low..high (3,) mapped by ``to_world`` (lines stay lines: identity or NDC)."""
    corners = torch.tensor([[x, y, z] for x in (0, 1) for y in (0, 1) for z in (0, 1)], dtype=torch.float32)
    corners = to_world(low + corners * (high - low)).float()
    edges = [(a, b) for a in range(8) for b in range(a + 1, 8) if bin(a ^ b).count("1") == 1]
    return torch.stack([torch.stack([corners[a], corners[b]]) for a, b in edges]).numpy()


def scene_box(model) -> np.ndarray | None:
    """(12, 2, 3) world edges of the part of the field's box (or its occupancy grid's) that has a place in the world: all
    of it for a bounded scene, the inner box of a contracted one, the box short of infinity in NDC; None without a box."""
    aabb = getattr(model.field, "aabb", None)
    grid = getattr(model.sampler, "grid", None)
    if not isinstance(aabb, torch.Tensor) and grid is not None:
        aabb = grid.aabb
    if not isinstance(aabb, torch.Tensor):
        return None
    low, high = model.space.bounded_box(aabb)
    ndc = model.space.ndc
    return _box_edges(low, high, (lambda p: p) if ndc is None else (lambda p: ndc.to_world(p.double())))


def occupied_cells(model, limit: int = 100_000) -> tuple[np.ndarray, float] | None:
    """(M, 3) world centres of the occupancy grid's occupied cells (at most ``limit``, evenly thinned; for a contracted
    scene those of the inner box) and the cell size; None for a sampler without an occupancy grid."""
    grid = getattr(model.sampler, "grid", None)
    if grid is None:
        return None
    centres = grid.cell_centres()[grid.binary].detach().float().cpu()  # (M, 3) field space
    space = model.space
    if space.contraction is not None:
        centres = centres[(centres.abs() <= 1.0).all(dim=-1)]
    if space.ndc is not None:
        centres = centres[centres[:, 2] < space.ndc.mesh_far_z]
        centres = space.ndc.to_world(centres.double()).float()
    if centres.shape[0] > limit:
        centres = centres[torch.linspace(0, centres.shape[0] - 1, limit).long()]
    size = float((grid.aabb[3:] - grid.aabb[:3]).min()) / grid.resolution
    return centres.numpy(), size


# -- the viewer --------------------------------------------------------------------------------------------------


@dataclass
class _Client:
    """What the viewer knows of one browser: its camera (version counts the updates) and how far it has rendered it."""

    camera: tuple | None = None  # (wxyz, position, fov_y, aspect, image_height)
    version: int = 0
    rendered_version: int = -1
    rendered_height: int = 0  # of the last frame of this version: refined until it is the ladder's last
    rendered_at: float = 0.0


class FieldViewer:
    """Serves a radiance field to the browsers connected to a viser ``server`` (see the module's docstring).

    Args:
        server: a ``viser.ViserServer``.
        model: a :class:`~nerf_lightning.models.RadianceFieldModule`, rendered on its device in eval mode.
        train_views: the training cameras and images, drawn as frustums; where the view starts.
        render_views: ``(path, frames) -> Views``, the cameras of a render path (a DataModule's ``render_views``).
        output_dir: the button's GIFs go to ``<output_dir>/<time>_<path>/`` (as nerf-render writes them).
        moving_frame_s: the time a frame may take while the camera moves; sets the first progressive resolution.
        max_resolution: the height, in pixels, of the last progressive frame (at most the browser's own).
        max_frame_s: refinements expected to take longer than this are skipped (the live view: every frame waits
            for training); None: refined up to ``max_resolution`` whatever it costs (a frame is dropped when the camera moves).
        refresh_s: render a camera again after this many seconds even when it has not moved (the live view: the
            field changes); None: never.
    """

    def __init__(self, server, model, train_views: Views, render_views: Callable[[str, int], Views], output_dir: str | Path,
                 moving_frame_s: float = 0.25, max_resolution: int = 512, max_frame_s: float | None = None,
                 refresh_s: float | None = None) -> None:
        if moving_frame_s <= 0 or max_resolution < 8:
            raise ValueError(f"the viewer needs moving_frame_s > 0 and max_resolution >= 8, got {moving_frame_s} and {max_resolution}")
        self.server, self.model, self.train_views, self.render_views = server, model, train_views, render_views
        self.output_dir = Path(output_dir)
        self.moving_frame_s, self.max_resolution = float(moving_frame_s), int(max_resolution)
        self.max_frame_s, self.refresh_s = max_frame_s, refresh_s
        self.rays_per_second = 20_000.0  # a cautious first guess; measured from every frame
        self.frames_rendered = 0
        self.last_frame: dict[int, dict] = {}  # client id -> {"picture", "height", "width", "output", "seconds"}
        self._clients: dict[int, _Client] = {}
        self._lock = threading.Lock()
        self._path_request: tuple[str, int, float] | None = None
        self._stop = threading.Event()
        self._build_scene()
        self._build_gui()
        server.on_client_connect(self._connect)
        server.on_client_disconnect(self._disconnect)

    # -- the page ------------------------------------------------------------------------------------------------

    def _build_scene(self) -> None:
        train = self.train_views
        centre, radius, up = scene_frame(train.c2w)
        self.radius = radius
        self.server.scene.set_up_direction(up.double().numpy())
        # start where the first training camera is, looking where the cameras look
        self.server.initial_camera.position = train.c2w[0, :3, 3].double().numpy()
        self.server.initial_camera.look_at = centre.double().numpy()
        self.server.initial_camera.fov = 2.0 * math.atan(0.5 * train.height / float(train.K[0, 1, 1]))
        self.frustums = add_training_cameras(self.server, train, radius, thumbnail_height=96)
        for index, frustum in enumerate(self.frustums):
            frustum.on_click(lambda event, index=index: self.look_through(event.client, index))
        self.box_handle = None
        self.cells_handle = None

    def _build_gui(self) -> None:
        gui = self.server.gui
        with gui.add_folder("View"):
            self.output = gui.add_dropdown("Show", OUTPUTS, initial_value="rgb")
            self.max_resolution_slider = gui.add_slider("Max height (px)", min=32, max=2048, step=16, initial_value=min(2048, self.max_resolution))
            self.stats = gui.add_markdown("waiting for the first frame")
        with gui.add_folder("Scene"):
            self.show_cameras = gui.add_checkbox("Training cameras", initial_value=True)
            self.show_box = gui.add_checkbox("Scene box", initial_value=False, disabled=scene_box(self.model) is None)
            has_grid = getattr(self.model.sampler, "grid", None) is not None
            self.show_cells = gui.add_checkbox("Occupied cells", initial_value=False, disabled=not has_grid)
        with gui.add_folder("Render path"):
            self.path = gui.add_dropdown("Path", PATHS, initial_value="orbit")
            self.path_frames = gui.add_number("Frames", initial_value=60, min=2, max=1000, step=1)
            self.path_scale = gui.add_number("Scale", initial_value=1.0, min=0.05, max=4.0, step=0.05)
            self.render_button = gui.add_button("Render to GIF")
            self.path_status = gui.add_markdown("")
        self.training = gui.add_markdown("")

        for control in (self.output, self.max_resolution_slider):
            control.on_update(lambda _: self._invalidate())
        self.show_cameras.on_update(lambda _: self._set_cameras_visible(self.show_cameras.value))
        self.show_box.on_update(lambda _: self.draw_box())
        self.show_cells.on_update(lambda _: self.draw_cells())
        for control in (self.path, self.path_frames):
            control.on_update(lambda _: self.draw_path())
        self.render_button.on_click(lambda _: self.request_path_render())
        self.draw_path()

    def _set_cameras_visible(self, visible: bool) -> None:
        for frustum in self.frustums:
            frustum.visible = visible

    def draw_path(self) -> None:
        """Draw the chosen render path: a line through its cameras, a point at each."""
        try:
            views = self.render_views(self.path.value, int(self.path_frames.value))
        except ValueError as error:
            self.path_status.content = f"no {self.path.value} path: {error}"
            return
        positions = views.c2w[:, :3, 3].float()
        segments = torch.stack([positions[:-1], positions[1:]], dim=1).numpy()
        self.server.scene.add_line_segments("/render_path/line", points=segments, colors=(230, 140, 20),
                                                               thickness=3.0, thickness_units="screen")
        self.server.scene.add_point_cloud("/render_path/cameras", points=positions.numpy(), colors=(230, 140, 20),
                                          point_size=0.02 * self.radius)

    def draw_box(self) -> None:
        if self.box_handle is not None:
            self.box_handle.remove()
            self.box_handle = None
        edges = scene_box(self.model) if self.show_box.value else None
        if edges is not None:
            self.box_handle = self.server.scene.add_line_segments("/scene_box", points=edges.astype(np.float32), colors=(200, 40, 160),
                                                                 thickness=2.0, thickness_units="screen")

    def draw_cells(self) -> None:
        if self.cells_handle is not None:
            self.cells_handle.remove()
            self.cells_handle = None
        cells = occupied_cells(self.model) if self.show_cells.value else None
        if cells is not None and len(cells[0]):
            points, size = cells
            self.cells_handle = self.server.scene.add_point_cloud("/occupied_cells", points=points.astype(np.float32), colors=(240, 120, 30),
                                                                  point_size=size, point_shape="square")

    def look_through(self, client, index: int) -> None:
        """Put ``client``'s camera where training camera ``index`` is, looking where it looks."""
        c2w = self.train_views.c2w[index].double()
        position, forward = c2w[:3, 3], c2w[:3, 2]
        fov_y = 2.0 * math.atan(0.5 * self.train_views.height / float(self.train_views.K[index, 1, 1]))
        with client.atomic():
            client.camera.fov = fov_y
            client.camera.position = position.numpy()
            client.camera.look_at = (position + self.radius * forward).numpy()
            client.camera.up_direction = (-c2w[:3, 1]).numpy()

    @property
    def path_requested(self) -> bool:
        """The page's Render button was pressed and that path is not rendered yet."""
        return self._path_request is not None

    def request_path_render(self) -> None:
        self._path_request = (self.path.value, int(self.path_frames.value), float(self.path_scale.value))
        self.path_status.content = f"rendering the {self.path.value} path..."

    # -- clients -------------------------------------------------------------------------------------------------

    def _connect(self, client) -> None:
        with self._lock:
            self._clients[client.client_id] = _Client()
        client.camera.on_update(self._camera_moved)

    def _disconnect(self, client) -> None:
        with self._lock:
            self._clients.pop(client.client_id, None)
            self.last_frame.pop(client.client_id, None)

    def _camera_moved(self, camera) -> None:
        snapshot = (camera.wxyz.copy(), camera.position.copy(), float(camera.fov), float(camera.aspect), int(camera.image_height))
        with self._lock:
            state = self._clients.get(camera.client.client_id)
            if state is not None:
                state.camera, state.version, state.rendered_height = snapshot, state.version + 1, 0

    def _invalidate(self) -> None:
        with self._lock:
            for state in self._clients.values():
                state.rendered_version, state.rendered_height = -1, 0

    def _next_job(self) -> tuple[int, _Client, int, bool] | None:
        """(client id, a copy of its state, its camera version, whether to refine), the most urgent first: a camera
        that moved, then one to refine, then (live) one due for a refresh."""
        now = time.monotonic()
        with self._lock:
            states = [(cid, s) for cid, s in self._clients.items() if s.camera is not None]
            for cid, state in states:
                if state.rendered_version != state.version:
                    return cid, _Client(**vars(state)), state.version, False
            for cid, state in states:
                if state.rendered_height < self._heights(state)[-1]:
                    return cid, _Client(**vars(state)), state.version, True
            if self.refresh_s is not None:
                for cid, state in states:
                    if now - state.rendered_at > self.refresh_s:
                        return cid, _Client(**vars(state)), state.version, False
        return None

    def _heights(self, state: _Client) -> list[int]:
        _, _, _, aspect, browser_height = state.camera
        max_height = max(8, min(int(self.max_resolution_slider.value), browser_height))
        heights = progressive_heights(self.rays_per_second, self.moving_frame_s, aspect, max_height)
        if self.max_frame_s is not None:
            affordable = [h for h in heights[1:] if h * h * aspect <= self.rays_per_second * self.max_frame_s]
            heights = heights[:1] + affordable
        return heights

    # -- rendering -----------------------------------------------------------------------------------------------

    def render_next(self) -> float | None:
        """Render what is most wanted: a path requested by the button, else one frame for one browser. Returns the
        seconds it took, or None when nothing was wanted."""
        if self._path_request is not None:
            started = time.perf_counter()
            self._render_path(*self._path_request)
            self._path_request = None
            return time.perf_counter() - started
        job = self._next_job()
        if job is None:
            return None
        client_id, state, version, refine = job
        heights = self._heights(state)
        height = next((h for h in heights if h > state.rendered_height), heights[-1]) if refine else heights[0]
        K, c2w, height, width = browser_camera(*state.camera[:4], height)
        chunk = int(max(1024, min(getattr(self.model, "chunk_size", 4096), self.rays_per_second * self.moving_frame_s / 2)))

        def moved() -> bool:
            with self._lock:
                current = self._clients.get(client_id)
                return current is None or current.version != version

        started = time.perf_counter()
        frame = render_view(self.model, K, c2w, height, width, chunk, abort=moved)
        seconds = time.perf_counter() - started
        if frame is None:  # the camera moved or the browser left: that frame is no longer wanted
            return seconds
        measured = height * width / max(seconds, 1e-4)
        self.rays_per_second = measured if not self.frames_rendered else 0.5 * (self.rays_per_second + measured)
        self.frames_rendered += 1
        output = self.output.value
        picture = frame_picture(self.model, frame, output)
        client = self.server.get_clients().get(client_id)
        if client is None:
            return seconds
        client.scene.set_background_image(picture, format="jpeg", jpeg_quality=90)
        self.last_frame[client_id] = {"picture": picture, "height": height, "width": width, "output": output, "seconds": seconds}
        with self._lock:
            current = self._clients.get(client_id)
            if current is not None and current.version == version:
                current.rendered_version, current.rendered_height, current.rendered_at = version, height, time.monotonic()
        self.stats.content = (f"{output} {width}x{height} in {seconds:.2f} s (step {heights.index(height) + 1 if height in heights else len(heights)} of {len(heights)}), "
                              f"{self.rays_per_second / 1000:.0f}k rays/s")
        return seconds

    def _render_path(self, path: str, frames: int, scale: float) -> None:
        try:
            views = self.render_views(path, frames).scaled(scale)
            folder = self.output_dir / f"{datetime.now():%Y-%m-%d_%H-%M-%S}_{path}"
            write_path_renders(self.model, views, folder, desc=f"{path} path")
        except Exception as error:  # a wrong choice in the page is reported there; the viewer goes on
            log.warning("rendering the %s path failed: %s", path, error)
            self.path_status.content = f"the {path} path failed: {error}"
            return
        log.info("wrote %d %dx%d frames of the %s path to %s", len(views), views.width, views.height, path, folder)
        self.path_status.content = f"wrote {folder / 'rgb.gif'}"

    def serve_forever(self, idle_s: float = 0.01) -> None:
        """Render whatever the browsers want until :meth:`stop` (nerf-view's loop; Ctrl-C ends it too)."""
        while not self._stop.is_set():
            if self.render_next() is None:
                time.sleep(idle_s)

    def stop(self) -> None:
        self._stop.set()


class LiveViewer(Callback):
    """nerf-train ``viewer=true``: the field in the browser while it trains, rendered between training steps.

    Rendering takes at most ``time_share`` of the time since training started (a frame is skipped while the share is
    spent); frames are as :class:`FieldViewer` makes them, refined only up to what ``max_frame_s`` renders, and a
    camera that stays still is rendered again every ``refresh_s`` seconds, since the field changes. A browser that
    leaves costs nothing; an error in the viewer is logged once and training goes on without it.

    Args:
        host, port: where the page is served; checked when the callback is made, before any data is loaded.
        output_dir: the run's folder; the page's Render button writes GIFs to ``<output_dir>/renders/``.
    """

    def __init__(self, host: str = "127.0.0.1", port: int = 8080, output_dir: str | Path = ".", time_share: float = 0.1,
                 moving_frame_s: float = 0.1, max_resolution: int = 512, max_frame_s: float = 1.0, refresh_s: float = 2.0) -> None:
        if not 0.0 < time_share < 1.0:
            raise ValueError(f"viewer_time_share must lie between 0 and 1, got {time_share}")
        require_viser()
        check_port(host, port, "viewer_port")
        self.host, self.port, self.output_dir, self.time_share = host, int(port), Path(output_dir), float(time_share)
        self.options = dict(moving_frame_s=moving_frame_s, max_resolution=max_resolution, max_frame_s=max_frame_s, refresh_s=refresh_s)
        self.viewer: FieldViewer | None = None
        self.server = None
        self.rendering_seconds = 0.0
        self._started: float | None = None
        self._cells_drawn_at = 0.0

    def setup(self, trainer, pl_module, stage: str) -> None:
        if stage != "fit" or not trainer.is_global_zero or self.server is not None:
            return
        self.server = start_server(self.host, self.port, "viewer_")
        datamodule = trainer.datamodule
        datamodule.setup("fit")
        self.viewer = FieldViewer(self.server, pl_module, datamodule.scene.train, datamodule.render_views,
                                  self.output_dir / "renders", **self.options)
        log.info("live view of the training field at http://%s:%d", self.host, self.port)

    def on_train_start(self, trainer, pl_module) -> None:
        self._started = time.perf_counter()

    def on_train_batch_end(self, trainer, pl_module, outputs, batch, batch_idx) -> None:
        if self.viewer is None or self._started is None:
            return
        elapsed = time.perf_counter() - self._started
        if self.rendering_seconds > self.time_share * elapsed:
            return
        if not self.server.get_clients() and not self.viewer.path_requested:
            return
        started = time.perf_counter()
        was_training = pl_module.training
        sampler = getattr(pl_module, "sampler", None)
        bake_resolution = getattr(sampler, "bake_resolution", None)
        try:
            pl_module.eval()
            if bake_resolution is not None:  # the proposal networks change every step: a bake would not outlive the frame
                sampler.bake_resolution = None
            if self.viewer.show_cells.value and time.monotonic() - self._cells_drawn_at > self.options["refresh_s"] * 5:
                self.viewer.draw_cells()  # the occupancy grid changes as the field trains
                self._cells_drawn_at = time.monotonic()
            psnr = trainer.callback_metrics.get("train/psnr")
            self.viewer.render_next()
            self.viewer.training.content = (f"training: step {trainer.global_step}" + ("" if psnr is None else f", train PSNR {float(psnr):.2f} dB")
                                            + f"; {self.viewer.frames_rendered} frames rendered")
        except Exception as error:  # the view is a convenience: training never stops for it
            log.warning("the live viewer stopped (%s: %s); training goes on without it", type(error).__name__, error)
            self.close()
        finally:
            pl_module.train(was_training)
            if bake_resolution is not None:
                sampler.bake_resolution = bake_resolution
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

    def teardown(self, trainer, pl_module, stage: str) -> None:
        self.close()

    def on_exception(self, trainer, pl_module, exception: BaseException) -> None:
        self.close()
