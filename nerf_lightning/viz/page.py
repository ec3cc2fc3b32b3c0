"""The viewer's page in the browser (viser): the scene around the render and the controls beside it.

The scene: the training cameras as frustums showing their images (click one to look through it), the render path in
orange, and whatever the model offers to draw (:class:`~nerf_lightning.models.contract.ShowsOverlays`: a checkbox
each; none for a model that offers nothing), and, for a model of Gaussians
(:class:`~nerf_lightning.models.contract.HasGaussians`), the Gaussians themselves drawn by the browser
(:mod:`nerf_lightning.viz.splats`). The controls: what draws the view of a model of Gaussians (the browser's splats,
or rendered frames), what a frame shows (rgb, depth, accumulation), the largest height of a frame, the render path
and its Render-to-GIF button, the camera path a user frames (:mod:`~nerf_lightning.viz.keyframes`: keyframes, a preview,
camera_path.json), a line on the last frame (or the splats) and one on training.

The page renders nothing: it tells its owner what changed through the callbacks it is given.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from pathlib import Path

import numpy as np
import torch

from nerf_lightning.data.choices import RENDER_PATHS
from nerf_lightning.data.scene import Views
from nerf_lightning.models.contract import HasGaussians, Overlay, ShowsOverlays, implements
from nerf_lightning.viz.keyframes import KeyframePanel
from nerf_lightning.viz.splats import SplatArrays
from nerf_lightning.viz.viser_view import add_training_cameras, scene_frame

OUTPUTS = ("rgb", "depth", "accumulation")
# what draws the view of a model of Gaussians: the browser itself (viser's splats, degree-0 colours), or the model's
# renders (every colour band, depth and accumulation), as for any other model
SPLATS, FRAMES = "browser splats", "rendered frames"
DRAWN_BY = (SPLATS, FRAMES)
PATHS = RENDER_PATHS
PATH_COLOUR = (230, 140, 20)


class ViewerPage:
    """The scene and the controls of the viewer on a viser ``server``.

    Args:
        server: a ``viser.ViserServer``.
        model: asked for its overlays when it is :class:`~nerf_lightning.models.contract.ShowsOverlays`; a
            :class:`~nerf_lightning.models.contract.HasGaussians` gets the "Drawn by" control (its splats are drawn
            through :meth:`draw_splats`, by the owner).
        train_views: the training cameras and images, drawn as frustums; where the view starts.
        render_views: ``(path, frames) -> Views``, the cameras of a render path (a DataModule's ``render_views``).
        max_resolution: the initial value of the "Max height" slider.
        on_view_changed: called when what a frame shows changes (the output, the largest height).
        on_render_path: called with (path, frames, scale) when the Render-to-GIF button is pressed.
        on_drawn_by_changed: called when "Drawn by" changes (a model of Gaussians), after the page has shown or
            hidden the splats.
        camera_paths_dir: where the "Camera path" folder saves camera_path.json (None: the working directory).
    """

    def __init__(self, server, model, train_views: Views, render_views: Callable[[str, int], Views], max_resolution: int,
                 on_view_changed: Callable[[], None], on_render_path: Callable[[str, int, float], None],
                 on_drawn_by_changed: Callable[[], None] | None = None, camera_paths_dir: str | Path | None = None) -> None:
        self.server, self.model, self.train_views, self.render_views = server, model, train_views, render_views
        self._on_view_changed, self._on_render_path = on_view_changed, on_render_path
        self._on_drawn_by_changed = on_drawn_by_changed
        self.overlay_handles: dict[str, object] = {}
        self.has_gaussians = implements(model, HasGaussians)
        self.splat_handle = None  # the browser's splats, once drawn (draw_splats)
        self.splats_text = "the Gaussians are on their way"
        self._build_scene()
        self._build_gui(max_resolution)
        world_from_capture = model.space.world_from_capture
        self.keyframes = KeyframePanel(server, train_views.height, train_views.width, self.radius, Path(camera_paths_dir or "."),
                                       None if world_from_capture is None else world_from_capture.cpu())

    # -- building ------------------------------------------------------------------------------------------------

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

    def _build_gui(self, max_resolution: int) -> None:
        gui = self.server.gui
        with gui.add_folder("View"):
            # None for a model without Gaussians: its view is always rendered frames
            self.drawn_by = gui.add_dropdown("Drawn by", DRAWN_BY, initial_value=SPLATS) if self.has_gaussians else None
            self.output = gui.add_dropdown("Show", OUTPUTS, initial_value="rgb", disabled=self.splats_drawn)
            self.max_resolution = gui.add_slider("Max height (px)", min=32, max=2048, step=16, initial_value=min(2048, max_resolution))
            self.stats = gui.add_markdown(self.splats_text if self.splats_drawn else "waiting for the first frame")
        names = self.model.overlay_names() if implements(self.model, ShowsOverlays) else {}
        with gui.add_folder("Scene"):
            self.show_cameras = gui.add_checkbox("Training cameras", initial_value=True)
            self.overlay_boxes = {name: gui.add_checkbox(label, initial_value=False) for name, label in names.items()}
        with gui.add_folder("Render path"):
            self.path = gui.add_dropdown("Path", PATHS, initial_value="orbit")
            self.path_frames = gui.add_number("Frames", initial_value=60, min=2, max=1000, step=1)
            self.path_scale = gui.add_number("Scale", initial_value=1.0, min=0.05, max=4.0, step=0.05)
            self.render_button = gui.add_button("Render to GIF")
            self.path_status = gui.add_markdown("")
        self.training = gui.add_markdown("")

        for control in (self.output, self.max_resolution):
            control.on_update(lambda _: self._on_view_changed())
        if self.drawn_by is not None:
            self.drawn_by.on_update(lambda _: self._drawn_by_chosen())
        self.show_cameras.on_update(lambda _: self.set_cameras_visible(self.show_cameras.value))
        for name, box in self.overlay_boxes.items():
            box.on_update(lambda _, name=name: self.draw_overlay(name))
        for control in (self.path, self.path_frames):
            control.on_update(lambda _: self.draw_path())
        self.render_button.on_click(lambda _: self._render_pressed())
        self.draw_path()

    # -- the scene -----------------------------------------------------------------------------------------------

    @property
    def splats_drawn(self) -> bool:
        """The browser draws the model's Gaussians itself (a model of Gaussians, "Drawn by" its splats): no frame is
        rendered for the view."""
        return self.drawn_by is not None and self.drawn_by.value == SPLATS

    def draw_splats(self, arrays: SplatArrays) -> None:
        """Send the Gaussians ``arrays`` to the browsers under ``/splats`` (replacing those sent before; shown while
        "Drawn by" is the splats) and say in the page how many are drawn."""
        if arrays.shown == 0:
            if self.splat_handle is not None:
                self.splat_handle.remove()
                self.splat_handle = None
        else:
            self.splat_handle = self.server.scene.add_gaussian_splats(
                "/splats", centers=arrays.centers, covariances=arrays.covariances, rgbs=arrays.rgbs,
                opacities=arrays.opacities, visible=self.splats_drawn)
        self.splats_text = arrays.describe()
        if self.splats_drawn:
            self.stats.content = self.splats_text

    def _drawn_by_chosen(self) -> None:
        splats = self.splats_drawn
        if self.splat_handle is not None:
            self.splat_handle.visible = splats
        self.output.disabled = splats  # what a frame shows: no frame while the browser draws the splats
        self.stats.content = self.splats_text if splats else "waiting for the first frame"
        if self._on_drawn_by_changed is not None:
            self._on_drawn_by_changed()

    def set_cameras_visible(self, visible: bool) -> None:
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
        self.server.scene.add_line_segments("/render_path/line", points=segments, colors=PATH_COLOUR, thickness=3.0,
                                            thickness_units="screen")
        self.server.scene.add_point_cloud("/render_path/cameras", points=positions.numpy(), colors=PATH_COLOUR,
                                          point_size=0.02 * self.radius)

    def draw_overlay(self, name: str) -> None:
        """Draw the model's overlay ``name`` as it is now if its box is checked; remove it otherwise."""
        handle = self.overlay_handles.pop(name, None)
        if handle is not None:
            handle.remove()
        overlay = self.model.overlay(name) if self.overlay_boxes[name].value else None
        if overlay is not None and len(overlay.points):
            self.overlay_handles[name] = self._add_overlay(f"/overlays/{name}", overlay)

    def redraw_overlays(self) -> None:
        """Draw again every checked overlay (the live view: the model changes as it trains)."""
        for name, box in self.overlay_boxes.items():
            if box.value:
                self.draw_overlay(name)

    def _add_overlay(self, node: str, overlay: Overlay):
        points = np.asarray(overlay.points, dtype=np.float32)
        if overlay.kind == "lines":
            return self.server.scene.add_line_segments(node, points=points, colors=overlay.colour, thickness=overlay.size,
                                                       thickness_units="screen")
        if overlay.kind == "points":
            return self.server.scene.add_point_cloud(node, points=points, colors=overlay.colour, point_size=overlay.size,
                                                     point_shape="square")
        raise ValueError(f"an overlay is lines or points, not '{overlay.kind}' ({overlay.label})")

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

    # -- the controls ------------------------------------------------------------------------------------------

    def _render_pressed(self) -> None:
        self.path_status.content = f"rendering the {self.path.value} path..."
        self._on_render_path(self.path.value, int(self.path_frames.value), float(self.path_scale.value))
