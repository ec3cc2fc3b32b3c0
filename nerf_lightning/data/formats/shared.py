"""What the loaders share, in one place: the similarity that normalises a capture's cameras (transforms.json and LLFF
captures) and the cache the built-in scenes are rendered into once (procedural and turntable)."""

from __future__ import annotations

import os
import shutil
import tempfile
from collections.abc import Callable
from pathlib import Path

import torch

from nerf_lightning.geometry.cameras import opengl_to_opencv
from nerf_lightning.geometry.paths import look_at_point


CENTRES = ("focus", "poses", "none")


def normalising_transform(c2w: torch.Tensor, centre: str = "focus") -> torch.Tensor:
    """(N, 4, 4) OpenGL cameras -> (4, 4) similarity: centre on the cameras' focus (``focus``), on their mean
    centre (``poses``) or not at all (``none``); mean up to +z; farthest camera coordinate 1.

    ``focus`` falls back to ``poses`` where the cameras do not look towards a common point (it would lie behind them)."""
    if centre not in CENTRES:
        raise ValueError(f"data.scene.centre must be one of {CENTRES}, got '{centre}'")
    c2w = c2w.double()
    origins = c2w[:, :3, 3]
    if centre == "focus":
        focus = look_at_point(opengl_to_opencv(c2w))
        in_front = float(((focus - origins) * -c2w[:, :3, 2]).sum(-1).mean()) > 0  # OpenGL cameras look down -z
        centre_point = focus if in_front else origins.mean(0)
    else:
        centre_point = origins.mean(0) if centre == "poses" else torch.zeros(3, dtype=torch.float64)
    up = torch.nn.functional.normalize(c2w[:, :3, 1].mean(0), dim=0)
    # the rotation taking ``up`` to +z (Rodrigues), as nerfstudio's rotation_matrix(up, [0, 0, 1])
    z = torch.tensor([0.0, 0.0, 1.0], dtype=torch.float64)
    axis, cosine = torch.linalg.cross(up, z), float(up @ z)
    if cosine < -1.0 + 1e-9:
        rotation = torch.diag(torch.tensor([1.0, -1.0, -1.0], dtype=torch.float64))
    else:
        skew = torch.tensor([[0.0, -axis[2], axis[1]], [axis[2], 0.0, -axis[0]], [-axis[1], axis[0], 0.0]], dtype=torch.float64)
        rotation = torch.eye(3, dtype=torch.float64) + skew + skew @ skew / (1.0 + cosine)
    transform = torch.eye(4, dtype=torch.float64)
    transform[:3, :3], transform[:3, 3] = rotation, -rotation @ centre_point
    reach = float((transform[:3, :3] @ c2w[:, :3, 3].T + transform[:3, 3:]).abs().max())
    scale = 1.0 / reach if reach > 1e-9 else 1.0  # cameras all at the centre (one camera): nothing to scale by
    return torch.diag(torch.tensor([scale, scale, scale, 1.0], dtype=torch.float64)) @ transform


def apply_similarity(transform: torch.Tensor, c2w: torch.Tensor) -> torch.Tensor:
    """A (4, 4) similarity applied to (N, 4, 4) cameras, their rotations kept orthonormal; float64 out."""
    transform = transform.double()
    scale = transform[:3, :3].det().abs() ** (1.0 / 3.0)
    out = c2w.double().clone()
    out[:, :3, :3] = (transform[:3, :3] / scale) @ c2w[:, :3, :3].double()
    out[:, :3, 3] = (transform[:3, :3] @ c2w[:, :3, 3].double().T + transform[:3, 3:]).T
    return out


def every_frame_or_none(path: Path, frames: list[tuple[int, dict, Path]], key: str, what: str) -> bool:
    """Whether the json's ``frames`` ((number, frame, image path)) give ``key`` (a frame's ``mask_path``,
    ``depth_file_path``); False where none does. ValueError naming the frames without it where only some have it
    (``what``: what a frame is then asked for, "its mask")."""
    without = [str(frame["file_path"]) for _, frame, _ in frames if frame.get(key) is None]
    if len(without) == len(frames):
        return False
    if without:
        raise ValueError(f"{path}: {len(frames) - len(without)} frames have a '{key}' but {len(without)} do not "
                         f"({', '.join(without[:5])}{' ...' if len(without) > 5 else ''}): give every frame {what}, or none")
    return True


def default_cache() -> Path:
    return Path(os.environ.get("NERF_LIGHTNING_CACHE", Path.home() / ".cache" / "nerf_lightning"))


def rendered_once(root: Path, marker: str, make: Callable[[Path], object]) -> Path:
    """``root``, rendered by ``make(folder)`` where ``root/marker`` is not there yet: into a staging folder beside it,
    then renamed, so that a reader never sees half a scene and processes rendering it at once keep the first."""
    if not (root / marker).is_file():
        root.parent.mkdir(parents=True, exist_ok=True)
        staging = Path(tempfile.mkdtemp(dir=root.parent, prefix=f".{root.name}."))
        try:
            make(staging)
            try:
                staging.rename(root)
            except OSError:  # another process made it first
                if not (root / marker).is_file():
                    raise
        finally:
            shutil.rmtree(staging, ignore_errors=True)
    return root
