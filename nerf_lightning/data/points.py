"""Sparse 3D points of a capture (what structure from motion triangulated), with their colours, for models that
start from them (Gaussian splats are placed at them).

Two sources, both in the capture's coordinates, mapped into the scene's world by the loader's
``world_from_capture``: a PLY point cloud (x, y, z and red, green, blue: nerfstudio's ``ply_file_path``, what
``nerf-process-data`` writes) and a COLMAP sparse model's ``points3D.bin`` / ``points3D.txt``.
"""

from __future__ import annotations

import struct
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

GREY = 128


@dataclass
class SparsePoints:
    """Points of a scene's world.

    Attributes:
        positions: (P, 3) float32, in the scene's world (the loader's normalisation applied).
        colours: (P, 3) uint8 RGB.
    """

    positions: torch.Tensor
    colours: torch.Tensor

    def __post_init__(self) -> None:
        count = self.positions.shape[0]
        if self.positions.shape != (count, 3) or self.colours.shape != (count, 3):
            raise ValueError(f"SparsePoints need positions (P, 3) and colours (P, 3) with one P, got {tuple(self.positions.shape)} "
                             f"and {tuple(self.colours.shape)}")
        if self.positions.dtype != torch.float32 or self.colours.dtype != torch.uint8:
            raise ValueError(f"SparsePoints need float32 positions and uint8 colours, got {self.positions.dtype} and {self.colours.dtype}")

    def __len__(self) -> int:
        return int(self.positions.shape[0])

    @classmethod
    def mapped(cls, positions: np.ndarray, colours: np.ndarray, world_from_capture: torch.Tensor | None = None) -> SparsePoints:
        """(P, 3) positions in a capture's coordinates, mapped by the (4, 4) affine ``world_from_capture`` (None:
        kept) in float64, and (P, 3) uint8 colours -> the points of the scene's world."""
        positions = torch.from_numpy(np.asarray(positions, dtype=np.float64).reshape(-1, 3))
        if world_from_capture is not None:
            transform = torch.as_tensor(world_from_capture, dtype=torch.float64)
            positions = positions @ transform[:3, :3].T + transform[:3, 3]
        return cls(positions.float(), torch.from_numpy(np.asarray(colours, dtype=np.uint8).reshape(-1, 3)))


def read_ply_points(path: str | Path, world_from_capture: torch.Tensor | None = None) -> SparsePoints:
    """A PLY's vertices (x, y, z) and their colours (red, green, blue; grey where the file has none), read with
    trimesh and mapped by ``world_from_capture`` (see :meth:`SparsePoints.mapped`). ValueError naming the file
    when it is missing or not a readable PLY."""
    import trimesh

    path = Path(path)
    if not path.is_file():
        raise ValueError(f"sparse points not found: {path}")
    try:
        loaded = trimesh.load(path, file_type="ply", process=False)
    except Exception as error:  # trimesh raises whatever its parser met
        raise ValueError(f"could not read the sparse points in {path}: {type(error).__name__}: {error}") from None
    vertices = np.asarray(getattr(loaded, "vertices", np.zeros((0, 3))), dtype=np.float64).reshape(-1, 3)
    return SparsePoints.mapped(vertices, _vertex_colours(loaded, len(vertices)), world_from_capture)


def _vertex_colours(loaded, count: int) -> np.ndarray:
    """(count, 3) uint8 RGB of a trimesh point cloud or mesh, grey where it has none."""
    colours = getattr(loaded, "colors", None)  # a PointCloud
    if colours is None or len(colours) != count:
        visual = getattr(loaded, "visual", None)  # a Trimesh
        colours = getattr(visual, "vertex_colors", None) if getattr(visual, "kind", None) == "vertex" else None
    if colours is None or len(colours) != count:
        return np.full((count, 3), GREY, dtype=np.uint8)
    return np.asarray(colours)[:, :3].astype(np.uint8)


def read_colmap_points(folder: str | Path, world_from_capture: torch.Tensor | None = None) -> SparsePoints | None:
    """The 3D points of a COLMAP sparse model (``folder/points3D.bin``, else ``points3D.txt``), mapped from
    COLMAP's world by ``world_from_capture`` (see :meth:`SparsePoints.mapped`); None where the folder has neither.
    ValueError naming the file when it cannot be read."""
    folder = Path(folder)
    binary, text = folder / "points3D.bin", folder / "points3D.txt"
    try:
        if binary.is_file():
            return SparsePoints.mapped(*_read_points3d_bin(binary), world_from_capture)
        if text.is_file():
            return SparsePoints.mapped(*_read_points3d_txt(text), world_from_capture)
    except (OSError, ValueError, struct.error, IndexError) as error:
        raise ValueError(f"could not read the COLMAP points in {binary if binary.is_file() else text}: {error}") from None
    return None


def _read_points3d_bin(path: Path) -> tuple[np.ndarray, np.ndarray]:
    """COLMAP's binary points: a uint64 count, then per point id (uint64), xyz (3 float64), rgb (3 uint8),
    error (float64), a uint64 track length and that many (image id, point2D index) uint32 pairs."""
    data = path.read_bytes()
    (count,), at = struct.unpack_from("<Q", data, 0), 8
    positions, colours = np.empty((count, 3)), np.empty((count, 3), dtype=np.uint8)
    for index in range(count):
        values = struct.unpack_from("<Q3d3Bd", data, at)
        positions[index], colours[index] = values[1:4], values[4:7]
        (track,) = struct.unpack_from("<Q", data, at + 43)
        at += 51 + 8 * track
    if at != len(data):
        raise ValueError(f"{len(data) - at} bytes beyond its {count} points")
    return positions, colours


def _read_points3d_txt(path: Path) -> tuple[np.ndarray, np.ndarray]:
    """COLMAP's text points: ``POINT3D_ID X Y Z R G B ERROR TRACK[]`` a line, ``#`` comments."""
    rows = [line.split() for line in path.read_text().splitlines() if line.strip() and not line.startswith("#")]
    positions = np.array([[float(value) for value in row[1:4]] for row in rows], dtype=np.float64).reshape(-1, 3)
    colours = np.array([[int(value) for value in row[4:7]] for row in rows], dtype=np.uint8).reshape(-1, 3)
    return positions, colours
