"""Camera paths as files: nerfstudio's ``camera_path.json`` (what its viewer exports and ``ns-render camera-path``
reads; ``nerf-view``'s keyframes save the same) and the ``transforms.json`` of a path this project rendered, read into
cameras in a scene's world, and written from them.

nerfstudio's format: ``render_height``, ``render_width``, ``fps``, ``seconds`` and ``camera_path``, one entry a frame,
with ``camera_to_world`` (16 numbers: a 4x4 matrix row by row, of an OpenGL camera, x right, y up, looking down -z),
``fov`` (vertical, in degrees) and ``aspect``. The principal point is the image's centre and the focal length
``0.5 * render_height / tan(fov / 2)``, as ``ns-render`` computes them; the frame's size is the file's (``aspect`` is
not read, as ``ns-render`` does not read it). The viewer adds its ``keyframes``; only ``perspective`` cameras are read.

Coordinates. A path's cameras are in the capture's own coordinates, those of its ``transforms.json`` or
``poses_bounds.npy`` (LLFF's axes turned to OpenGL's, as its loader turns them), so a training camera copied into a
path renders that photo; they are mapped into the scene's world by the scene's ``world_from_capture``. A path
exported from nerfstudio's viewer is in nerfstudio's normalised world instead: its ``dataparser_transforms.json``
(``transform``, 3x4, and ``scale``: nerfstudio's world = scale * (transform @ capture's)) maps it back.
"""

from __future__ import annotations

import json
import math
from pathlib import Path
from typing import Any

import torch

from nerf_lightning.data.formats.shared import apply_similarity
from nerf_lightning.data.formats.transforms import frame_intrinsics
from nerf_lightning.data.scene import Views
from nerf_lightning.geometry.cameras import centred_intrinsics, opengl_to_opencv, validate_c2w

NOT_A_PATH = ("expected nerfstudio's camera_path.json (render_height, render_width and a camera_path list) or the "
              "transforms.json of a rendered path (w, h and a frames list)")


def _read_json(path: Path, what: str) -> Any:
    if not path.is_file():
        raise FileNotFoundError(f"{path}: no such {what} file")
    try:
        return json.loads(path.read_text())
    except (json.JSONDecodeError, UnicodeDecodeError) as error:
        raise ValueError(f"{path}: not a {what}: it is not JSON ({error})") from None


def _matrices(values: list, path: Path, key: str) -> torch.Tensor:
    """(N, 4, 4) from N lists of 16 numbers (row by row) or N 4x4 nested lists, checked rigid and finite."""
    try:
        c2w = torch.tensor(values, dtype=torch.float64).reshape(len(values), 4, 4)
    except (TypeError, ValueError, RuntimeError):
        raise ValueError(f"{path}: every {key} must be 16 numbers (a 4x4 matrix row by row)") from None
    return validate_c2w(c2w, f"{path} {key}").double()


def _number(mapping: dict, key: str, path: Path, low: float = 0.0, high: float = math.inf) -> float:
    value = mapping.get(key)
    if not isinstance(value, (int, float)) or isinstance(value, bool) or not math.isfinite(value) or not low < value < high:
        raise ValueError(f"{path}: '{key}' must be a number in ({low:g}, {high:g}), got {value!r}")
    return float(value)


def read_dataparser_transforms(path: str | Path) -> torch.Tensor:
    """nerfstudio's ``dataparser_transforms.json`` (``transform`` 3x4, ``scale``) -> (4, 4) float64, the similarity
    from nerfstudio's normalised world back to the capture's coordinates."""
    path = Path(path)
    meta = _read_json(path, "dataparser_transforms.json")
    try:
        transform = torch.tensor(meta["transform"], dtype=torch.float64)
        scale = float(meta["scale"])
    except (KeyError, TypeError, ValueError):
        raise ValueError(f"{path}: expected nerfstudio's dataparser_transforms.json, with 'transform' (3x4) and 'scale'") from None
    if transform.shape != (3, 4) or not torch.isfinite(transform).all() or not (math.isfinite(scale) and scale > 0):
        raise ValueError(f"{path}: 'transform' must be 3x4 and finite and 'scale' a positive number")
    nerfstudio_from_capture = torch.eye(4, dtype=torch.float64)
    nerfstudio_from_capture[:3] = scale * transform
    return torch.linalg.inv(nerfstudio_from_capture)


def read_camera_path(path: str | Path, world_from_capture: torch.Tensor | None = None,
                     dataparser_transforms: str | Path | None = None) -> tuple[Views, float | None]:
    """A camera path file (see the module's docstring) -> its cameras in the scene's world (:class:`Views` without
    images, OpenCV c2w) and its frames a second (None where the file says none). ``world_from_capture`` (4, 4): the
    scene's, None for a scene in the capture's own coordinates; ``dataparser_transforms``: nerfstudio's file, for a path
    in nerfstudio's normalised world."""
    path = Path(path)
    meta = _read_json(path, "camera path")
    if not isinstance(meta, dict):
        raise ValueError(f"{path}: not a camera path: {NOT_A_PATH}")
    if "camera_path" in meta:
        c2w, K, height, width = _nerfstudio_path(meta, path)
        fps = _number(meta, "fps", path) if "fps" in meta else None
    elif "frames" in meta:
        c2w, K, height, width = _rendered_path(meta, path)
        fps = None
    else:
        raise ValueError(f"{path}: not a camera path: {NOT_A_PATH}")
    if dataparser_transforms is not None:
        c2w = apply_similarity(read_dataparser_transforms(dataparser_transforms), c2w)
    if world_from_capture is not None:
        c2w = apply_similarity(torch.as_tensor(world_from_capture).double(), c2w)
    views = Views(K=K.float(), c2w=opengl_to_opencv(c2w).float(), height=height, width=width,
                  names=[f"frame_{index:04d}" for index in range(len(c2w))])
    return views, fps


def _nerfstudio_path(meta: dict, path: Path) -> tuple[torch.Tensor, torch.Tensor, int, int]:
    camera_type = meta.get("camera_type", "perspective")
    if camera_type != "perspective":
        raise ValueError(f"{path}: camera_type '{camera_type}': only perspective camera paths can be rendered")
    height, width = round(_number(meta, "render_height", path)), round(_number(meta, "render_width", path))
    cameras = meta["camera_path"]
    if not isinstance(cameras, list) or not cameras or not all(isinstance(camera, dict) for camera in cameras):
        raise ValueError(f"{path}: 'camera_path' must be a non-empty list of cameras, each with camera_to_world and fov")
    missing = [index for index, camera in enumerate(cameras) if "camera_to_world" not in camera or "fov" not in camera]
    if missing:
        raise ValueError(f"{path}: camera_path[{missing[0]}] has no 'camera_to_world' or no 'fov'")
    c2w = _matrices([camera["camera_to_world"] for camera in cameras], path, "camera_path[].camera_to_world")
    fov = torch.tensor([_number(camera, "fov", path, high=180.0) for camera in cameras], dtype=torch.float64)
    focal = 0.5 * height / torch.tan(0.5 * torch.deg2rad(fov))
    return c2w, centred_intrinsics(focal, height, width), height, width


def _rendered_path(meta: dict, path: Path) -> tuple[torch.Tensor, torch.Tensor, int, int]:
    height, width = round(_number(meta, "h", path)), round(_number(meta, "w", path))
    frames = meta["frames"]
    if not isinstance(frames, list) or not frames or not all(isinstance(frame, dict) and "transform_matrix" in frame for frame in frames):
        raise ValueError(f"{path}: 'frames' must be a non-empty list of frames, each with a transform_matrix")
    c2w = _matrices([frame["transform_matrix"] for frame in frames], path, "frames[].transform_matrix")
    K = torch.stack([frame_intrinsics(frame, meta, width, height, path, f"frame {index}: ")[0] for index, frame in enumerate(frames)])
    return c2w, K.double(), height, width


def camera_path_meta(views: Views, world_from_capture: torch.Tensor | None, fps: float,
                     keyframes: list[dict] | None = None) -> dict:
    """Cameras in the scene's world (OpenCV c2w, one focal length each) -> nerfstudio's ``camera_path.json``, in the
    capture's coordinates (the inverse of ``world_from_capture``), with ``keyframes`` (nerfstudio's viewer's: ``matrix``,
    ``fov``, ``aspect``) where given."""
    c2w = opengl_to_opencv(views.c2w.double())
    if world_from_capture is not None:
        c2w = apply_similarity(torch.linalg.inv(torch.as_tensor(world_from_capture).double()), c2w)
    fov = torch.rad2deg(2.0 * torch.atan(0.5 * views.height / views.K[:, 1, 1].double()))
    aspect = views.width / views.height
    cameras = [{"camera_to_world": matrix.flatten().tolist(), "fov": float(angle), "aspect": aspect} for matrix, angle in zip(c2w, fov)]
    return {"camera_type": "perspective", "render_height": views.height, "render_width": views.width, "fps": fps,
            "seconds": len(cameras) / fps, "keyframes": keyframes or [], "camera_path": cameras}
