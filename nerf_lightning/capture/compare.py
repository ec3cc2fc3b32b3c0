"""Recovered cameras against published ones of the same photos (a ``transforms.json`` against a ``transforms.json`` or
an LLFF ``poses_bounds.npy``), after the similarity that best aligns their centres, fitted again without the
cameras far off it (:func:`nerf_lightning.geometry.alignment.camera_pose_errors`)."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import torch

from nerf_lightning.capture.images import IMAGE_SUFFIXES, natural_key
from nerf_lightning.data.formats.llff import read_poses_bounds
from nerf_lightning.geometry.alignment import camera_pose_errors


def cameras_by_image(path: str | Path) -> dict[str, torch.Tensor]:
    """A capture's cameras: image stem -> (4, 4) OpenGL camera-to-world (float64), from a ``transforms.json``
    (its frames' ``transform_matrix``) or from an LLFF ``poses_bounds.npy`` (a row an image of the capture's
    ``images*/`` folder, in name order, as LLFF writes them). Stems, so that ``IMG_1.JPG`` and a copy of it written
    as ``IMG_1.png`` are one photo."""
    path = Path(path)
    if path.is_dir():
        path = path / "transforms.json" if (path / "transforms.json").is_file() or not (path / "poses_bounds.npy").is_file() \
            else path / "poses_bounds.npy"
    if path.suffix == ".npy":
        return llff_cameras_by_image(path)
    frames = json.loads(path.read_text())["frames"]
    return {Path(frame["file_path"]).stem: torch.tensor(frame["transform_matrix"], dtype=torch.float64) for frame in frames}


def llff_cameras_by_image(path: Path) -> dict[str, torch.Tensor]:
    """``poses_bounds.npy`` -> image stem -> (4, 4) OpenGL camera-to-world; the names from the first ``images*/`` folder
    beside it that holds as many images as the file has rows."""
    c2w, _, _ = read_poses_bounds(path)
    c2w = torch.cat([torch.from_numpy(c2w), torch.tensor([0.0, 0.0, 0.0, 1.0], dtype=torch.float64).expand(len(c2w), 1, 4)], dim=1)
    for folder in sorted(path.parent.glob("images*")):
        names = sorted((file.stem for file in folder.iterdir() if file.suffix.lower() in IMAGE_SUFFIXES), key=natural_key)
        if len(names) == len(c2w):
            return dict(zip(names, c2w))
    raise ValueError(f"{path}: no images*/ folder beside it holds its {len(c2w)} images, so its rows cannot be named")


def compare_with_reference(recovered: str | Path, reference: str | Path) -> dict[str, Any]:
    """Cameras of ``recovered`` against those of ``reference`` for the images both have (matched by file name).

    Returns the number compared, the number the similarity was fitted to (``aligned_on``: those not far off it), the medians and maxima of the position error (in the reference's units and as a
    percentage of the reference cameras' spread, the root mean square distance of their centres from their mean) and
    of the rotation error in degrees, the spread, and the per-image errors.
    """
    ours, theirs = cameras_by_image(recovered), cameras_by_image(reference)
    common = sorted(set(ours) & set(theirs), key=natural_key)
    if len(common) < 3:
        raise ValueError(f"{recovered} and {reference} share {len(common)} images; comparing cameras needs 3 or more")
    errors = camera_pose_errors(torch.stack([ours[name] for name in common]), torch.stack([theirs[name] for name in common]))
    position, rotation, spread = errors["position_error"], errors["rotation_error"], float(errors["spread"])
    return {
        "compared": len(common),
        "aligned_on": int(errors["aligned_on"].sum()),
        "spread": spread,
        "median_position_error": float(position.median()),
        "median_position_error_percent_of_spread": 100.0 * float(position.median()) / spread,
        "max_position_error_percent_of_spread": 100.0 * float(position.max()) / spread,
        "median_rotation_error_deg": float(rotation.median()),
        "max_rotation_error_deg": float(rotation.max()),
        "per_image": {name: {"position_error_percent_of_spread": round(100.0 * float(p) / spread, 4), "rotation_error_deg": round(float(r), 4)}
                      for name, p, r in zip(common, position, rotation)},
    }
