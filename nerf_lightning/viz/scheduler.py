"""What the viewer renders next: the browsers' cameras, the progressive heights of each, the rays a second measured.

No browser and no viser here: the page tells a :class:`RenderScheduler` that a camera moved (:meth:`camera_moved`),
asks it for the most wanted frame (:meth:`next_job`) and reports the frame done (:meth:`rendered`). A camera that
moved is rendered first, at the height that the measured rays per second render within ``moving_frame_s``; once it
stops it is refined, twice the height each time, up to the largest (:func:`progressive_heights`); a frame is
dropped when its camera moves on (:meth:`is_stale`, the render's ``abort``).
"""

from __future__ import annotations

import math
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, replace

import kornia
import numpy as np
import torch


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


@dataclass(frozen=True)
class BrowserCamera:
    """One browser's camera as viser reports it: orientation ``wxyz`` (4,) and ``position`` (3,) of an OpenCV camera
    in the world, vertical field of view ``fov_y`` in radians, ``aspect`` width / height, the page's ``image_height``
    in pixels (no frame is rendered larger)."""

    wxyz: np.ndarray
    position: np.ndarray
    fov_y: float
    aspect: float
    image_height: int


@dataclass
class _Client:
    """What the scheduler knows of one browser: its camera (``version`` counts its updates) and how far it has been
    rendered."""

    camera: BrowserCamera | None = None
    version: int = 0
    rendered_version: int = -1
    rendered_height: int = 0  # of the last frame of this version: refined until it is the ladder's last
    rendered_at: float = 0.0


@dataclass(frozen=True)
class Job:
    """One frame to render: browser ``client_id``'s camera as of ``version``, ``height`` pixels high, step ``step``
    (1-based) of ``steps`` progressive heights."""

    client_id: int
    version: int
    camera: BrowserCamera
    height: int
    step: int
    steps: int

    def pinhole(self) -> tuple[torch.Tensor, torch.Tensor, int, int]:
        """K (3, 3), OpenCV c2w (4, 4), height, width of this frame."""
        camera = self.camera
        return browser_camera(camera.wxyz, camera.position, camera.fov_y, camera.aspect, self.height)


class RenderScheduler:
    """The browsers' cameras and the frames they want, most urgent first (thread-safe: viser reports cameras from
    its own threads while one thread renders).

    Args:
        moving_frame_s: the time a frame may take while the camera moves; sets the first progressive height.
        max_resolution: the height, in pixels, of the last progressive frame (at most the browser's own); the page's
            slider sets it.
        max_frame_s: refinements expected to take longer than this are skipped (the live view: every frame waits
            for training); None: refined up to ``max_resolution`` whatever it costs.
        refresh_s: a camera that has not moved is rendered again after this many seconds (the live view: the field
            changes); None: never.
        clock: seconds, monotonic (tests pass their own).
    """

    def __init__(self, moving_frame_s: float = 0.25, max_resolution: int = 512, max_frame_s: float | None = None,
                 refresh_s: float | None = None, clock: Callable[[], float] = time.monotonic) -> None:
        if moving_frame_s <= 0 or max_resolution < 8:
            raise ValueError(f"the viewer needs moving_frame_s > 0 and max_resolution >= 8, got {moving_frame_s} and {max_resolution}")
        self.moving_frame_s, self.max_resolution = float(moving_frame_s), int(max_resolution)
        self.max_frame_s, self.refresh_s, self.clock = max_frame_s, refresh_s, clock
        self.rays_per_second = 20_000.0  # a cautious first guess; measured from every frame
        self.frames_rendered = 0
        self._clients: dict[int, _Client] = {}
        self._lock = threading.Lock()

    # -- what the page reports -----------------------------------------------------------------------------------

    def connect(self, client_id: int) -> None:
        with self._lock:
            self._clients[client_id] = _Client()

    def disconnect(self, client_id: int) -> None:
        with self._lock:
            self._clients.pop(client_id, None)

    def camera_moved(self, client_id: int, camera: BrowserCamera) -> None:
        with self._lock:
            state = self._clients.get(client_id)
            if state is not None:
                state.camera, state.version, state.rendered_height = camera, state.version + 1, 0

    def invalidate(self) -> None:
        """Every camera wants new frames from the first height (what is shown, or the largest height, changed)."""
        with self._lock:
            for state in self._clients.values():
                state.rendered_version, state.rendered_height = -1, 0

    # -- what the renderer asks ----------------------------------------------------------------------------------

    def heights(self, camera: BrowserCamera) -> list[int]:
        """The progressive heights of ``camera`` at the rays per second measured so far."""
        max_height = max(8, min(self.max_resolution, camera.image_height))
        heights = progressive_heights(self.rays_per_second, self.moving_frame_s, camera.aspect, max_height)
        if self.max_frame_s is not None:
            affordable = [h for h in heights[1:] if h * h * camera.aspect <= self.rays_per_second * self.max_frame_s]
            heights = heights[:1] + affordable
        return heights

    def next_job(self) -> Job | None:
        """The most wanted frame: of a camera that moved (at the first height), else of one to refine (the next
        height), else (with ``refresh_s``) of one due for a refresh; None when every camera is rendered."""
        now = self.clock()
        with self._lock:
            states = [(cid, replace(s)) for cid, s in self._clients.items() if s.camera is not None]
        for cid, state in states:
            if state.rendered_version != state.version:
                return self._job(cid, state, 0)
        for cid, state in states:
            heights = self.heights(state.camera)
            if state.rendered_height < heights[-1]:
                return self._job(cid, state, next(i for i, h in enumerate(heights) if h > state.rendered_height))
        if self.refresh_s is not None:
            for cid, state in states:
                if now - state.rendered_at > self.refresh_s:
                    return self._job(cid, state, 0)
        return None

    def _job(self, client_id: int, state: _Client, step: int) -> Job:
        heights = self.heights(state.camera)
        return Job(client_id, state.version, state.camera, heights[step], step + 1, len(heights))

    def is_stale(self, job: Job) -> bool:
        """The job's camera moved on, or its browser left: the frame is no longer wanted (a render's ``abort``)."""
        with self._lock:
            state = self._clients.get(job.client_id)
            return state is None or state.version != job.version

    def rendered(self, job: Job, width: int, seconds: float) -> None:
        """``job`` was rendered (``width`` pixels wide) in ``seconds``: measure the rays per second, and mark its
        camera rendered at that height unless it moved meanwhile."""
        measured = job.height * width / max(seconds, 1e-4)
        self.rays_per_second = measured if not self.frames_rendered else 0.5 * (self.rays_per_second + measured)
        self.frames_rendered += 1
        with self._lock:
            state = self._clients.get(job.client_id)
            if state is not None and state.version == job.version:
                state.rendered_version, state.rendered_height, state.rendered_at = job.version, job.height, self.clock()

    def settled(self, client_id: int) -> bool:
        """``client_id``'s camera is rendered at its last progressive height."""
        with self._lock:
            state = self._clients.get(client_id)
            if state is None or state.camera is None or state.rendered_version != state.version:
                return False
            camera, rendered_height = state.camera, state.rendered_height
        return rendered_height >= self.heights(camera)[-1]

    def camera(self, client_id: int) -> BrowserCamera | None:
        with self._lock:
            state = self._clients.get(client_id)
            return None if state is None else state.camera

    def version(self, client_id: int) -> int:
        with self._lock:
            state = self._clients.get(client_id)
            return -1 if state is None else state.version
