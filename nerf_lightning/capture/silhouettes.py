"""Do a masked capture's poses agree with its masks? The check ``nerf-process-data masks=...`` makes before it
writes a model.

COLMAP can string photos that are too far apart into a model that is wrong: its reprojection error is low and it
explains most of the few matches it has, yet the cameras are in the wrong places. A masked capture has a test that
does not lean on the matches: the masks' visual hull. Where the poses are right, the hull carved by all the masks is
the object, and every mask pixel's ray meets it. Where they are wrong, the masks do not agree, the hull is a scrap
or nothing, and most rays miss it (:func:`~nerf_lightning.data.object_box.silhouette_coverage`).

The hull is carved on a grid over the sparse points' box (the points were matched inside the masks, so they lie on
the object, in a wrong model too), from the smallest mask copies of about :data:`MASK_SIDE` pixels.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np
import torch
from PIL import Image

from nerf_lightning.data.object_box import silhouette_coverage, visual_hull

# the masks are read at about this long side (the copy of the capture's smallest downscale that reaches it)
MASK_SIDE = 480
# the hull's grid, points a side over the sparse points' box, widened by BOX_MARGIN of its size a side
RESOLUTION = 64
BOX_MARGIN = 0.5
# a view whose mask's rays meet the hull less than this is one the poses place wrong
VIEW_BELOW = 0.5
# OpenGL (nerfstudio's transform_matrix) to OpenCV camera axes: y and z flipped
GL_TO_CV = np.diag([1.0, -1.0, -1.0, 1.0])


def mask_copy(staging: Path, downscales: list[int], size: tuple[int, int]) -> tuple[Path, int]:
    """The masks folder to read (``masks`` or ``masks_<k>``) and its factor: the largest k whose masks keep a long
    side of :data:`MASK_SIDE` or more."""
    usable = [k for k in sorted(downscales, reverse=True) if max(size) / k >= MASK_SIDE and (staging / f"masks_{k}").is_dir()]
    return (staging / f"masks_{usable[0]}", usable[0]) if usable else (staging / "masks", 1)


def silhouette_agreement(transforms: dict[str, Any], points: np.ndarray, staging: Path, downscales: list[int],
                         seed: int = 0) -> dict[str, Any]:
    """Each registered photo's coverage (the fraction of its mask's rays that meet the masks' visual hull), their
    median, and the photos under :data:`VIEW_BELOW`.

    Args:
        transforms: what :func:`~nerf_lightning.capture.colmap.reconstruction_to_transforms` wrote (frames with
            ``transform_matrix`` and ``mask_path``; the shared camera's ``fl_x``, ``fl_y``, ``cx``, ``cy``, ``w``, ``h``).
        points: (P, 3) the model's sparse points in its world.
        staging: the folder holding the written ``masks/`` and ``masks_<k>/``.
        downscales: the factors of those copies.
    """
    width, height = int(transforms["w"]), int(transforms["h"])
    folder, factor = mask_copy(staging, list(downscales), (width, height))
    frames = transforms["frames"]
    masks = torch.from_numpy(np.stack([np.asarray(Image.open(folder / Path(frame["mask_path"]).name)) > 127 for frame in frames]))
    if masks.ndim == 4:  # a mask saved with colour channels
        masks = masks.any(-1)
    K = torch.tensor([[transforms["fl_x"] / factor, 0.0, transforms["cx"] / factor], [0.0, transforms["fl_y"] / factor, transforms["cy"] / factor],
                      [0.0, 0.0, 1.0]], dtype=torch.float64).expand(len(frames), 3, 3)
    c2w = torch.from_numpy(np.stack([np.asarray(frame["transform_matrix"], dtype=np.float64) @ GL_TO_CV for frame in frames]))
    if len(points) >= 4:
        low, high = np.percentile(points, 2, axis=0), np.percentile(points, 98, axis=0)
    else:  # no points to say where the object is: the cameras' box
        centres = c2w[:, :3, 3].numpy()
        low, high = centres.min(0), centres.max(0)
    widen = BOX_MARGIN * (high - low).max()
    low, high = torch.from_numpy(low - widen), torch.from_numpy(high + widen)
    hull = visual_hull(c2w, K, masks, low, high, RESOLUTION)
    coverage = silhouette_coverage(c2w, K, masks, hull, low, high, generator=torch.Generator().manual_seed(seed))
    names = [Path(frame["file_path"]).name for frame in frames]
    return {"median_coverage": round(float(coverage.median()), 4),
            "coverage": {name: round(float(value), 4) for name, value in zip(names, coverage)},
            "views_below": [name for name, value in zip(names, coverage) if value < VIEW_BELOW],
            "masks_read": f"{folder.name} ({int(masks.shape[2])}x{int(masks.shape[1])})"}
