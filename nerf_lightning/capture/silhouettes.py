"""Do a masked capture's poses agree with its masks? The check ``nerf-process-data masks=...`` makes before it
writes a model.

COLMAP can string photos that are too far apart into a model that is wrong: its reprojection error is low and it
explains most of the few matches it has, yet the cameras are in the wrong places. A masked capture has a test that
does not lean on the matches: the masks' visual hull. Where the poses are right, the hull carved by all the masks is
the object, and every mask pixel's ray meets it. Where they are wrong, the masks do not agree, the hull is a scrap
or nothing, and most rays miss it (:func:`~nerf_lightning.data.object_box.silhouette_coverage`).

The hull is carved on a grid over the sparse points' box (the points were matched inside the masks, so they lie on
the object, in a wrong model too; where the hull reaches the box's faces, in a wider box), from masks of about
:data:`MASK_SIDE` pixels (the smallest copy that reaches it, or the masks cut to blocks).
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np
import torch

from nerf_lightning.capture.images import read_mask
from nerf_lightning.data.formats.lenses import FISHEYE_KEYS, FISHEYE_MODELS, FisheyeLens
from nerf_lightning.data.images import downscale_mask
from nerf_lightning.data.object_box import silhouette_coverage, visual_hull
from nerf_lightning.geometry.cameras import opengl_to_opencv

# the masks are read at about this long side (the copy of the capture's smallest downscale that reaches it)
MASK_SIDE = 480
# the hull's grid, points a side over the sparse points' box, widened by BOX_MARGIN of its size a side
RESOLUTION = 64
BOX_MARGIN = 0.5
# a hull that touches its box's faces is carved again in a box twice as wide, this many times at most
GROW_TRIES = 3
# a view whose mask's rays meet the hull less than this is one the poses place wrong
VIEW_BELOW = 0.5


def mask_copy(staging: Path, downscales: list[int], long_side: int) -> tuple[Path, int]:
    """The masks folder to read (``masks`` or ``masks_<k>``) and its factor: the largest k whose masks of photos
    ``long_side`` pixels long keep a long side of :data:`MASK_SIDE` or more."""
    usable = [k for k in sorted(downscales, reverse=True) if long_side / k >= MASK_SIDE and (staging / f"masks_{k}").is_dir()]
    return (staging / f"masks_{usable[0]}", usable[0]) if usable else (staging / "masks", 1)


def carving_box(points: np.ndarray, c2w: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """(3,), (3,) float64: the box to carve the hull in: the sparse points' (P, 3) (those between their 2nd and 98th
    percentiles: strays left out), widened by :data:`BOX_MARGIN` of its longest side; the cameras' (c2w (N, 4, 4)) where
    the points are too few or all in one place."""
    low = high = None
    if len(points) >= 4:
        low, high = np.percentile(points, 2, axis=0), np.percentile(points, 98, axis=0)
    centres = c2w[:, :3, 3].numpy()
    spread = float((centres.max(0) - centres.min(0)).max())
    if low is None or (high - low).max() <= 1e-3 * spread:
        low, high = centres.min(0), centres.max(0)
    widen = BOX_MARGIN * (high - low).max()
    return torch.from_numpy(low - widen), torch.from_numpy(high + widen)


def pinhole_mask(frame: dict[str, Any], mask: torch.Tensor, factor: int) -> tuple[torch.Tensor, torch.Tensor]:
    """A frame's mask (h, w) bool, read at 1/``factor`` of its photo's size, and the K (3, 3) float64 of the pinhole
    camera to carve it with: the frame's own K for COLMAP's OpenCV family (their small distortion left in), and for an
    ``OPENCV_FISHEYE`` frame the mask undistorted onto the pinhole view the loader trains on
    (:class:`~nerf_lightning.data.formats.lenses.FisheyeLens`): a fisheye's rim lies far from where a pinhole puts it."""
    K = torch.tensor([[frame["fl_x"] / factor, 0.0, frame["cx"] / factor], [0.0, frame["fl_y"] / factor, frame["cy"] / factor],
                      [0.0, 0.0, 1.0]], dtype=torch.float64)
    if frame.get("camera_model") not in FISHEYE_MODELS:
        return mask, K
    pinhole_K, lens = FisheyeLens(tuple(float(frame[key]) for key in FISHEYE_KEYS)).pinhole(K, *mask.shape)
    return lens.undistort(mask[..., None].float(), pinhole_K)[..., 0] >= 0.5, pinhole_K


def silhouette_agreement(transforms: dict[str, Any], points: np.ndarray, staging: Path, downscales: list[int],
                         seed: int = 0) -> dict[str, Any]:
    """Each registered photo's coverage (the fraction of its mask's rays that meet the masks' visual hull), their
    median, and the photos under :data:`VIEW_BELOW`.

    Args:
        transforms: what :func:`~nerf_lightning.capture.reconstruction.reconstruction_to_transforms` wrote: frames with
            ``transform_matrix`` (OpenGL) and ``mask_path``, the intrinsics (``fl_x``, ``fl_y``, ``cx``, ``cy``, ``w``,
            ``h``) shared at the top or a frame's own.
        points: (P, 3) the model's sparse points in its world.
        staging: the folder holding the written ``masks/`` and ``masks_<k>/``.
        downscales: the factors of those copies.
    """
    frames = [{**transforms, **frame} for frame in transforms["frames"]]  # a frame's own intrinsics where it has them
    largest = max(max(int(frame["w"]), int(frame["h"])) for frame in frames)
    folder, factor = mask_copy(staging, list(downscales), largest)
    # no copy small enough (downscales=[]): each mask cut to blocks as it is read, so that 12 MP photos cost no more
    blocks = max(1, largest // factor // MASK_SIDE)
    read = [downscale_mask(torch.from_numpy(read_mask(folder / Path(frame["mask_path"]).name)), blocks) for frame in frames]
    factor *= blocks
    read, K = zip(*(pinhole_mask(frame, mask, factor) for frame, mask in zip(frames, read)))
    # photos of several sizes (a camera each): masks padded with background, which counts as outside the frame
    height, width = max(mask.shape[0] for mask in read), max(mask.shape[1] for mask in read)
    masks = torch.zeros(len(read), height, width, dtype=torch.bool)
    for index, mask in enumerate(read):
        masks[index, :mask.shape[0], :mask.shape[1]] = mask
    K = torch.stack(K)
    c2w = opengl_to_opencv(torch.tensor([frame["transform_matrix"] for frame in frames], dtype=torch.float64))
    low, high = carving_box(points, c2w)
    for attempt in range(GROW_TRIES):  # a hull cut off by its grid's box (points on a part of the object alone): a wider box
        hull = visual_hull(c2w, K, masks, low, high, RESOLUTION)
        touches = hull[[0, -1]].any() or hull[:, [0, -1]].any() or hull[:, :, [0, -1]].any()
        if not touches or attempt == GROW_TRIES - 1:
            break
        centre, half = (low + high) / 2, (high - low) / 2
        low, high = centre - 2.0 * half, centre + 2.0 * half
    coverage = silhouette_coverage(c2w, K, masks, hull, low, high, generator=torch.Generator().manual_seed(seed))
    names = [Path(frame["file_path"]).name for frame in frames]
    return {"median_coverage": round(float(coverage.median()), 4),
            "coverage": {name: round(float(value), 4) for name, value in zip(names, coverage)},
            "views_below": [name for name, value in zip(names, coverage) if value < VIEW_BELOW],
            "masks_read": f"{folder.name}" + (f" in blocks of {blocks}" if blocks > 1 else "") + f" (up to {width}x{height})"}
