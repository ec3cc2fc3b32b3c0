"""nerf-export: a mesh of a radiance field by marching cubes on its density, with vertex colours (PLY or OBJ)."""

from __future__ import annotations

import logging
from pathlib import Path

import hydra
import numpy as np
import torch
from omegaconf import DictConfig

from nerf_lightning.checkpoints import load_model
from nerf_lightning.io import to_uint8, write_atomic

log = logging.getLogger(__name__)


@torch.no_grad()
def density_grid(density_fn, low: torch.Tensor, high: torch.Tensor, resolution: int, chunk: int = 65_536) -> torch.Tensor:
    """Density sampled at the (resolution,) * 3 corners of a grid spanning the box [low, high]: (R, R, R)."""
    axes = [torch.linspace(float(low[i]), float(high[i]), resolution) for i in range(3)]
    points = torch.stack(torch.meshgrid(*axes, indexing="ij"), dim=-1).reshape(-1, 3)
    values = torch.cat([density_fn(part) for part in points.split(chunk)])
    return values.reshape(resolution, resolution, resolution)


def marching_cubes(grid: torch.Tensor, threshold: float, low: torch.Tensor, high: torch.Tensor) -> tuple[np.ndarray, np.ndarray]:
    """The ``threshold`` level set of a (R, R, R) grid over [low, high]: vertices (V, 3) in world units, faces (F, 3)."""
    import mcubes

    vertices, faces = mcubes.marching_cubes(grid.numpy().astype(np.float64), threshold)
    scale = ((high - low) / (grid.shape[0] - 1)).numpy()
    return vertices * scale + low.numpy(), faces.astype(np.int64)


def vertex_colours(field, vertices: np.ndarray, chunk: int = 16_384) -> np.ndarray:
    """Colours (V, 3) uint8 of the field at the vertices, seen from outside: along the density's gradient
    (density rises into the surface, so the gradient points the way a ray looking at it travels)."""
    colours = []
    for part in torch.from_numpy(vertices).float().split(chunk):
        points = part.clone().requires_grad_(True)
        with torch.enable_grad():
            gradient = torch.autograd.grad(field.density(points).sum(), points)[0]
        direction = torch.nn.functional.normalize(gradient, dim=-1)
        with torch.no_grad():
            colours.append(field(points.detach(), direction)["rgb"])
    return to_uint8(torch.cat(colours) if colours else torch.zeros(0, 3))


def ply_bytes(vertices: np.ndarray, faces: np.ndarray, colours: np.ndarray) -> bytes:
    """A binary little-endian PLY with vertex colours."""
    header = (
        "ply\nformat binary_little_endian 1.0\n"
        f"element vertex {len(vertices)}\nproperty float x\nproperty float y\nproperty float z\n"
        "property uchar red\nproperty uchar green\nproperty uchar blue\n"
        f"element face {len(faces)}\nproperty list uchar int vertex_indices\nend_header\n"
    ).encode()
    vertex = np.zeros(len(vertices), dtype=[("xyz", "<f4", 3), ("rgb", "u1", 3)])
    vertex["xyz"], vertex["rgb"] = vertices, colours
    face = np.zeros(len(faces), dtype=[("n", "u1"), ("index", "<i4", 3)])
    face["n"], face["index"] = 3, faces
    return header + vertex.tobytes() + face.tobytes()


def read_ply_vertices(path: str | Path) -> tuple[np.ndarray, np.ndarray]:
    """Vertices (V, 3) float64 and colours (V, 3) uint8 of a PLY written by :func:`ply_bytes`."""
    header, body = Path(path).read_bytes().split(b"end_header\n", 1)
    count = int(header.split(b"element vertex ")[1].split()[0])
    vertex = np.frombuffer(body[: count * 15], dtype=[("xyz", "<f4", 3), ("rgb", "u1", 3)])
    return vertex["xyz"].astype(np.float64), vertex["rgb"].copy()


def obj_bytes(vertices: np.ndarray, faces: np.ndarray, colours: np.ndarray) -> bytes:
    """A Wavefront OBJ with per-vertex colours (``v x y z r g b``, as MeshLab reads them)."""
    lines = [f"v {x:.6f} {y:.6f} {z:.6f} {r / 255:.4f} {g / 255:.4f} {b / 255:.4f}" for (x, y, z), (r, g, b) in zip(vertices, colours)]
    lines += [f"f {a + 1} {b + 1} {c + 1}" for a, b, c in faces]
    return ("\n".join(lines) + "\n").encode()


def export(cfg: DictConfig) -> Path:
    model, info = load_model(cfg.ckpt_path, kind="radiance_field", command="nerf-export")
    if cfg.format not in ("ply", "obj"):
        raise ValueError(f"export format must be ply or obj, got '{cfg.format}'")
    field = model.fine_field or model.field  # the fine network has the sharper density
    low, high = torch.tensor(list(cfg.bounds[0]), dtype=torch.float32), torch.tensor(list(cfg.bounds[1]), dtype=torch.float32)
    grid = density_grid(field.density, low, high, cfg.resolution)
    vertices, faces = marching_cubes(grid, cfg.threshold, low, high)
    if len(faces) == 0:
        raise ValueError(f"no surface: the density never crosses export.threshold={cfg.threshold} in the box {cfg.bounds} "
                         f"(its range there is {float(grid.min()):.3g}..{float(grid.max()):.3g}); lower the threshold or move the box")
    colours = vertex_colours(field, vertices)
    encode = ply_bytes if cfg.format == "ply" else obj_bytes
    path = write_atomic(Path(cfg.output_dir) / f"mesh.{cfg.format}", encode(vertices, faces, colours))
    log.info("wrote %s: %d vertices, %d faces (grid %d^3, threshold %g)", path, len(vertices), len(faces), cfg.resolution, cfg.threshold)
    return path


@hydra.main(version_base="1.3", config_path="conf", config_name="export")
def main(cfg: DictConfig) -> None:
    export(cfg)


if __name__ == "__main__":
    main()
