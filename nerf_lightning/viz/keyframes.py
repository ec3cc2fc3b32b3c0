"""Framing a camera path in the viewer: keyframes taken from the browser's view, the path through them previewed as
frustums, and saved as nerfstudio's ``camera_path.json``, which ``nerf-render render.path=<file>`` renders.

:class:`Keyframes` holds the cameras and makes the path (:func:`~nerf_lightning.geometry.paths.keyframe_path`:
positions on a Catmull-Rom spline, rotations spherically interpolated, each keyframe an equal share of the time);
:class:`KeyframePanel` is its folder in the page. Cameras are kept in the scene's world, as the browser shows it, and
written in the capture's own coordinates (:func:`~nerf_lightning.data.formats.camera_path.camera_path_meta`).
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import torch

from nerf_lightning.data.formats.camera_path import camera_path_meta
from nerf_lightning.data.scene import Views
from nerf_lightning.geometry.cameras import centred_intrinsics
from nerf_lightning.geometry.paths import keyframe_path
from nerf_lightning.io import write_json
from nerf_lightning.viz.scheduler import browser_camera

KEYFRAME_COLOUR, PREVIEW_COLOUR = (200, 40, 160), (230, 140, 20)
MAX_PREVIEW_FRUSTUMS = 24  # the preview draws every frame of a short path, evenly spaced ones of a long one


class Keyframes:
    """Keyframes of a camera path in the scene's world: OpenCV c2w (4, 4) and vertical field of view in degrees each;
    the path's frames are ``height`` x ``width`` (the training views' size, so a render matches the photos)."""

    def __init__(self, height: int, width: int) -> None:
        self.height, self.width = int(height), int(width)
        self.c2w: list[torch.Tensor] = []
        self.fov_degrees: list[float] = []

    def __len__(self) -> int:
        return len(self.c2w)

    def add(self, c2w: torch.Tensor, fov_degrees: float) -> None:
        self.c2w.append(c2w.detach().float().cpu().clone())
        self.fov_degrees.append(float(fov_degrees))

    def remove(self, index: int) -> None:
        """Remove keyframe ``index`` (from 0); IndexError naming the keyframes there are."""
        if not 0 <= index < len(self):
            raise IndexError(f"there is no keyframe {index + 1}: the path has {len(self)}")
        del self.c2w[index], self.fov_degrees[index]

    def path(self, n_frames: int) -> Views:
        """The ``n_frames`` cameras of the path through the keyframes (:class:`Views` without images)."""
        if len(self) < 2:
            raise ValueError(f"a camera path needs at least two keyframes, the path has {len(self)}: add another view")
        c2w, fov = keyframe_path(torch.stack(self.c2w), torch.tensor(self.fov_degrees), n_frames)
        K = centred_intrinsics(0.5 * self.height / torch.tan(0.5 * torch.deg2rad(fov)), self.height, self.width)
        return Views(K=K, c2w=c2w, height=self.height, width=self.width)

    def camera_path(self, seconds: float, fps: float, world_from_capture: torch.Tensor | None) -> dict:
        """nerfstudio's ``camera_path.json`` of the path, ``seconds`` long at ``fps`` frames a second (at least two frames),
        in the capture's coordinates, with the keyframes."""
        n_frames = max(2, round(seconds * fps))
        keyframe_views = Views(K=torch.eye(3).repeat(len(self), 1, 1), c2w=torch.stack(self.c2w), height=self.height, width=self.width)
        keyframe_views.K[:, 1, 1] = 0.5 * self.height / torch.tan(0.5 * torch.deg2rad(torch.tensor(self.fov_degrees)))
        keyframes = [{"matrix": camera["camera_to_world"], "fov": camera["fov"], "aspect": camera["aspect"]}
                     for camera in camera_path_meta(keyframe_views, world_from_capture, fps)["camera_path"]]
        meta = camera_path_meta(self.path(n_frames), world_from_capture, fps, keyframes)
        meta["seconds"] = float(seconds)
        return meta


class KeyframePanel:
    """The page's "Camera path" folder: Add keyframe (the browser's current view), the list, Remove keyframe <n>, the
    path's seconds and frames a second, Preview path (the path's cameras as frustums) and Save camera_path.json (into
    ``folder``). ``world_from_capture`` (4, 4): the scene's, to write the path in the capture's coordinates."""

    def __init__(self, server, height: int, width: int, radius: float, folder: Path,
                 world_from_capture: torch.Tensor | None) -> None:
        self.server, self.radius, self.folder = server, radius, Path(folder)
        self.world_from_capture = world_from_capture
        self.keyframes = Keyframes(height, width)
        self.saved: Path | None = None
        gui = server.gui
        with gui.add_folder("Camera path"):
            self.add_button = gui.add_button("Add keyframe", hint="the view as the browser shows it now")
            self.listing = gui.add_markdown("no keyframes: frame a view, then Add keyframe")
            self.remove_index = gui.add_number("Keyframe", initial_value=1, min=1, step=1)
            self.remove_button = gui.add_button("Remove keyframe")
            self.seconds = gui.add_number("Seconds", initial_value=4.0, min=0.1, max=600.0, step=0.1)
            self.fps = gui.add_number("FPS", initial_value=24.0, min=1.0, max=120.0, step=1.0)
            self.preview = gui.add_checkbox("Preview path", initial_value=False)
            self.file_name = gui.add_text("File", initial_value="camera_path.json")
            self.save_button = gui.add_button("Save camera_path.json")
            self.status = gui.add_markdown("")
        self.add_button.on_click(lambda event: self.add_view(event.client))
        self.remove_button.on_click(lambda _: self._remove_pressed())
        for control in (self.seconds, self.fps, self.preview):
            control.on_update(lambda _: self.draw())
        self.save_button.on_click(lambda _: self._save_pressed())

    def add_view(self, client) -> None:
        """Add ``client``'s camera as it is now as the last keyframe."""
        camera = client.camera
        _, c2w, _, _ = browser_camera(camera.wxyz, camera.position, float(camera.fov), float(camera.aspect), 1)
        self.keyframes.add(c2w, math.degrees(float(camera.fov)))
        self.draw()

    def _remove_pressed(self) -> None:
        try:
            self.keyframes.remove(int(self.remove_index.value) - 1)
        except IndexError as error:
            self.status.content = str(error)
            return
        self.draw()

    def n_frames(self) -> int:
        return max(2, round(float(self.seconds.value) * float(self.fps.value)))

    def draw(self) -> None:
        """The list of keyframes, their frustums and, with Preview path, the path's."""
        listing = [f"{index + 1}. at ({', '.join(f'{value:.2f}' for value in c2w[:3, 3].tolist())}), fov {fov:.0f}°"
                   for index, (c2w, fov) in enumerate(zip(self.keyframes.c2w, self.keyframes.fov_degrees))]
        self.listing.content = "\n".join(listing) if listing else "no keyframes: frame a view, then Add keyframe"
        self.server.scene.remove_by_name("/camera_path")
        aspect = self.keyframes.width / self.keyframes.height
        for index, (c2w, fov) in enumerate(zip(self.keyframes.c2w, self.keyframes.fov_degrees)):
            self._frustum(f"/camera_path/keyframes/{index:03d}", c2w, math.radians(fov), aspect, KEYFRAME_COLOUR, 0.12)
        if not self.preview.value or len(self.keyframes) < 2:
            return
        views = self.keyframes.path(self.n_frames())
        shown = np.unique(np.linspace(0, len(views) - 1, min(len(views), MAX_PREVIEW_FRUSTUMS)).round().astype(int))
        for index in shown:
            fov = 2.0 * math.atan(0.5 * views.height / float(views.K[index, 1, 1]))
            self._frustum(f"/camera_path/preview/{index:04d}", views.c2w[index], fov, aspect, PREVIEW_COLOUR, 0.06)
        positions = views.c2w[:, :3, 3].float()
        self.server.scene.add_line_segments("/camera_path/line", points=torch.stack([positions[:-1], positions[1:]], dim=1).numpy(),
                                            colors=PREVIEW_COLOUR, thickness=3.0, thickness_units="screen")

    def _frustum(self, name: str, c2w: torch.Tensor, fov: float, aspect: float, colour: tuple, size: float) -> None:
        import viser.transforms

        matrix = c2w.double().numpy()
        self.server.scene.add_camera_frustum(name, fov=fov, aspect=aspect, scale=size * self.radius, color=colour,
                                             wxyz=viser.transforms.SO3.from_matrix(matrix[:3, :3]).wxyz, position=matrix[:3, 3])

    def save(self) -> Path:
        """Write the path as nerfstudio's camera_path.json into the panel's folder, under the File name; -> the file."""
        name = Path(str(self.file_name.value).strip() or "camera_path.json").name
        if not name.endswith(".json"):
            name += ".json"
        meta = self.keyframes.camera_path(float(self.seconds.value), float(self.fps.value), self.world_from_capture)
        self.saved = write_json(self.folder / name, meta)
        return self.saved

    def _save_pressed(self) -> None:
        try:
            path = self.save()
        except (ValueError, OSError) as error:
            self.status.content = f"not saved: {error}"
            return
        self.status.content = f"saved {path} ({self.n_frames()} frames); render it with nerf-render render.path={path}"
