"""A capture's depth maps (nerfstudio's per-frame ``depth_file_path`` in a ``transforms.json``), read into the
scene's depth: the distance along each pixel's unit ray, in the scene's world.

What a phone writes (Record3D, Polycam, ``ns-process-data record3d``): one depth map a frame, a 16-bit PNG in
millimetres or a ``.npy`` of floats in metres, often smaller than its photo (a LiDAR's 256x192 beside a 1920x1440
photo), holding each pixel's camera z (not the distance along its ray), 0 where the sensor has no reading. The values
are multiplied by ``depth_unit_scale_factor`` (the json's key, per frame or for all; nerfstudio's name) where the json
gives one, else by the file's own unit: 1e-3 for a PNG (millimetres, nerfstudio's default) and 1 for a ``.npy``
(metres; nerfstudio multiplies a ``.npy`` by its 1e-3 too, so a nerfstudio capture of ``.npy`` millimetres says
``"depth_unit_scale_factor": 0.001``). Then, as the photo is: resized to the photo's size (nearest value, the
pixel centres aligned) and downscaled with it, undistorted with it; scaled by the similarity the poses are
normalised with (``world_from_capture``'s scale); and each camera z turned into the distance along the pixel's unit
ray (:func:`~nerf_lightning.geometry.cameras.pixel_ray_lengths`). A pixel without a reading (0, negative, not
finite) is NaN: unknown, left out of losses and scores.
"""

from __future__ import annotations

from collections.abc import Callable
from functools import partial
from pathlib import Path
from typing import Any

import imageio.v3 as iio
import numpy as np
import torch
import torch.nn.functional as F

from nerf_lightning.data.formats.shared import every_frame_or_none
from nerf_lightning.data.images import read_pixels
from nerf_lightning.geometry.cameras import pixel_ray_lengths
from nerf_lightning.io import write_atomic

# what a depth file's values are multiplied by where the json gives no depth_unit_scale_factor: millimetres, metres
DEPTH_UNITS = {".png": 1e-3, ".npy": 1.0}


def read_depth_file(path: Path) -> np.ndarray:
    """(h, w) float64 the values of a depth map as stored: a single-channel 16-bit PNG or a 2D ``.npy`` of numbers.
    FileNotFoundError or ValueError naming the file where it is missing, unreadable or of another shape or type."""
    suffix = path.suffix.lower()
    if suffix not in DEPTH_UNITS:
        raise ValueError(f"depth map {path}: expected a 16-bit .png (millimetres) or a .npy (metres), got '{path.suffix}'")
    if suffix == ".npy":
        if not path.is_file():
            raise FileNotFoundError(f"depth map file not found: {path}")
        try:
            values = np.load(path, allow_pickle=False)
        except Exception as error:  # numpy raises several types for a truncated or foreign file
            raise ValueError(f"could not read depth map {path}: {error}") from error
    else:
        values = read_pixels(path, "depth map")
        if values.dtype != np.uint16:
            raise ValueError(f"depth map {path} is a PNG of {values.dtype}: expected 16-bit (millimetres)")
    if values.ndim == 3 and values.shape[-1] == 1:
        values = values[..., 0]
    if values.ndim != 2 or not (np.issubdtype(values.dtype, np.integer) or np.issubdtype(values.dtype, np.floating)):
        raise ValueError(f"depth map {path} has shape {tuple(values.shape)} of {values.dtype}: expected one channel of numbers (h, w)")
    return values.astype(np.float64)


def frame_depth(path: Path, unit_scale: float, K: torch.Tensor, height: int, width: int, full_size: tuple[int, int],
                world_scale: float, undistort: Callable[[torch.Tensor], torch.Tensor] | None = None) -> torch.Tensor:
    """(height, width) float32 distances along the pixels' unit rays in the scene's world of the depth map at ``path``
    (camera z times ``unit_scale`` in the capture's units), NaN where unknown, for a photo of ``full_size`` (H, W)
    loaded at ``height`` x ``width`` with intrinsics ``K`` (3, 3) (downscaled); ``undistort``: what undistorts the
    photo ((h, w, 3) -> (h, w, 3)), or None. ValueError naming the file where its aspect is not its photo's."""
    z = read_depth_file(path) * unit_scale
    rows, columns = z.shape
    if abs(rows * full_size[1] / columns - full_size[0]) > max(1.0, full_size[0] / rows):
        raise ValueError(f"depth map {path} is {columns}x{rows}, not the shape of its {full_size[1]}x{full_size[0]} photo")
    z = torch.from_numpy(z)
    z[~(torch.isfinite(z) & (z > 0))] = float("nan")
    # the nearest value, pixel centres aligned: a depth edge is not blurred into depths no surface has
    z = F.interpolate(z[None, None], size=(height, width), mode="nearest-exact")[0, 0]
    if undistort is not None:
        z = undistort(z[..., None].expand(-1, -1, 3))[..., 0]  # a NaN spreads to its neighbours: unknown there too
        z[~(z > 0)] = float("nan")  # pixels from outside the map
    return (z * world_scale * pixel_ray_lengths(K.double(), height, width)).float()


def capture_depths(path: Path, meta: dict, frames: list[tuple[int, dict, Path]], sizes: dict[Path, tuple[int, int]],
                   lenses: dict[Path, tuple[torch.Tensor, Any]], height: int, width: int,
                   world_from_capture: torch.Tensor,
                   undistort: Callable[[torch.Tensor, torch.Tensor, Any], torch.Tensor] | None = None) -> torch.Tensor | None:
    """(N, height, width) the depth maps of ``frames`` ((number, frame, image path), in the views' order) from their
    ``depth_file_path``, by :func:`frame_depth`; None where no frame has one. ``sizes``: each image's full (H, W);
    ``lenses``: its (K, lens), K downscaled; ``undistort(image, K, lens)``: the loader's. ValueError
    naming the frames without one where only some have one, and the key where a value is not a number or a name."""
    if not every_frame_or_none(path, frames, "depth_file_path", "its depth map"):
        return None
    world_scale = float(world_from_capture[:3, :3].double().det().abs() ** (1.0 / 3.0))
    depths = []
    for number, frame, image_path in frames:
        if not isinstance(frame["depth_file_path"], str):
            raise ValueError(f"{path}: frame {number}: 'depth_file_path' must be a file name, got {frame['depth_file_path']!r}")
        depth_path = path.parent / frame["depth_file_path"]
        unit_scale = frame.get("depth_unit_scale_factor", meta.get("depth_unit_scale_factor"))
        if unit_scale is None:
            unit_scale = DEPTH_UNITS.get(depth_path.suffix.lower(), 1.0)
        elif isinstance(unit_scale, bool) or not isinstance(unit_scale, (int, float)) or not unit_scale > 0:
            raise ValueError(f"{path}: frame {number}: 'depth_unit_scale_factor' must be a number > 0, got {unit_scale!r}")
        K, photo_lens = lenses[image_path]
        lens = partial(undistort, K=K, lens=photo_lens) if undistort is not None and photo_lens.distorts() else None
        depths.append(frame_depth(depth_path, float(unit_scale), K, height, width, sizes[image_path], world_scale, lens))
    return torch.stack(depths)


def write_depth_png(path: Path, z: torch.Tensor | np.ndarray) -> None:
    """(h, w) camera z in metres -> a 16-bit PNG of millimetres (0 where not finite or beyond 65.535 m), as phones
    write them; what :func:`read_depth_file` reads."""
    millimetres = np.nan_to_num(np.asarray(z, dtype=np.float64) * 1000.0, nan=0.0, posinf=0.0, neginf=0.0)
    millimetres = np.where((millimetres > 0) & (millimetres <= 65535), np.round(millimetres), 0).astype(np.uint16)
    write_atomic(path, iio.imwrite("<bytes>", millimetres, extension=".png"))
