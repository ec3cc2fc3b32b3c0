"""Recovered cameras against published ones of the same photos (two ``transforms.json`` files), after the
similarity that best aligns their centres (:func:`nerf_lightning.geometry.alignment.camera_pose_errors`)."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import torch

from nerf_lightning.data.capture.images import natural_key
from nerf_lightning.geometry.alignment import camera_pose_errors


def cameras_by_image(path: str | Path) -> dict[str, torch.Tensor]:
    """A transforms.json's frames: image file name -> (4, 4) ``transform_matrix`` (float64)."""
    path = Path(path)
    if path.is_dir():
        path = path / "transforms.json"
    frames = json.loads(path.read_text())["frames"]
    return {Path(frame["file_path"]).name: torch.tensor(frame["transform_matrix"], dtype=torch.float64) for frame in frames}


def compare_with_reference(recovered: str | Path, reference: str | Path) -> dict[str, Any]:
    """Cameras of ``recovered`` against those of ``reference`` for the images both have (matched by file name).

    Returns the number compared, the medians and maxima of the position error (in the reference's units and as a
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
        "spread": spread,
        "median_position_error": float(position.median()),
        "median_position_error_percent_of_spread": 100.0 * float(position.median()) / spread,
        "max_position_error_percent_of_spread": 100.0 * float(position.max()) / spread,
        "median_rotation_error_deg": float(rotation.median()),
        "max_rotation_error_deg": float(rotation.max()),
        "per_image": {name: {"position_error_percent_of_spread": round(100.0 * float(p) / spread, 4), "rotation_error_deg": round(float(r), 4)}
                      for name, p, r in zip(common, position, rotation)},
    }
