"""nerf-export: a mesh of a radiance field by marching cubes on its density, with vertex colours (PLY or OBJ).

The density is meshed in the model's own coordinates (the scene's world, or NDC for a forward-facing scene);
the vertices are then written in the capture's coordinates (``frame=capture``: NDC undone, the loader's
normalisation undone, so the mesh lies where the capture's cameras are) or left in the scene's (``frame=scene``).
"""

from __future__ import annotations

import logging
from pathlib import Path

import hydra
import kornia
import numpy as np
import torch
from omegaconf import DictConfig

from nerf_lightning.checkpoints import load_model
from nerf_lightning.errors import ensure_writable, report_errors
from nerf_lightning.geometry.rays import ndc_to_world
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


# a forward-facing scene's NDC box stops short of z = 1, which is infinitely far
NDC_FAR_Z = 0.95


def mesh_box(model, bounds) -> tuple[torch.Tensor, torch.Tensor]:
    """The box to mesh, low (3,) and high (3,) in the model's coordinates: ``bounds`` as given, else the field's
    own box (a grid field's ``aabb``; the inner box of a contracted one), else [-1.5, 1.5]^3; in NDC, z < 0.95."""
    if bounds is not None:
        low, high = torch.tensor(list(bounds[0]), dtype=torch.float32), torch.tensor(list(bounds[1]), dtype=torch.float32)
    elif hasattr(model.field, "aabb"):
        low, high = model.field.aabb[:3].float().cpu(), model.field.aabb[3:].float().cpu()
    else:
        low, high = torch.full((3,), -1.5), torch.full((3,), 1.5)
    if model.ndc:
        high = high.clone()
        high[2] = min(float(high[2]), NDC_FAR_Z)
    if not bool((high > low).all()):
        raise ValueError(f"export bounds must have low < high on every axis, got {low.tolist()} and {high.tolist()}")
    return low, high


def to_capture(model, vertices: np.ndarray) -> np.ndarray:
    """(V, 3) vertices in the model's coordinates -> (V, 3) in the capture's: NDC undone, then the loader's
    normalisation (``world_from_capture``) undone."""
    points = torch.from_numpy(vertices).double()
    if model.ndc:
        points = ndc_to_world(points, model.ndc["focal"], model.ndc["width"], model.ndc["height"], model.ndc["near_plane"])
    if model.world_from_capture is not None:
        capture_from_world = torch.linalg.inv(model.world_from_capture.double())
        points = kornia.geometry.transform_points(capture_from_world[None], points[None])[0]
    return points.numpy()


def export(cfg: DictConfig) -> Path:
    model, info = load_model(cfg.ckpt_path, kind="radiance_field", command="nerf-export")
    ensure_writable(cfg.output_dir, "output_dir")
    if cfg.format not in ("ply", "obj"):
        raise ValueError(f"export format must be ply or obj, got '{cfg.format}'")
    if cfg.frame not in ("capture", "scene"):
        raise ValueError(f"export frame must be capture or scene, got '{cfg.frame}'")
    field = model.fine_field or model.field  # the fine network has the sharper density
    low, high = mesh_box(model, cfg.bounds)
    grid = density_grid(field.density, low, high, cfg.resolution)
    vertices, faces = marching_cubes(grid, cfg.threshold, low, high)
    if len(faces) == 0:
        raise ValueError(f"no surface: the density never crosses threshold={cfg.threshold} in the box {low.tolist()}..{high.tolist()} "
                         f"(its range there is {float(grid.min()):.3g}..{float(grid.max()):.3g}); lower the threshold or move the box")
    colours = vertex_colours(field, vertices)
    if cfg.frame == "capture":
        vertices = to_capture(model, vertices)
    encode = ply_bytes if cfg.format == "ply" else obj_bytes
    path = write_atomic(Path(cfg.output_dir) / f"mesh.{cfg.format}", encode(vertices, faces, colours))
    log.info("wrote %s: %d vertices, %d faces (grid %d^3 over %s..%s, threshold %g, %s coordinates)", path, len(vertices), len(faces),
             cfg.resolution, low.tolist(), high.tolist(), cfg.threshold, cfg.frame)
    return path


@hydra.main(version_base="1.3", config_path="conf", config_name="export")
@report_errors("nerf-export")
def main(cfg: DictConfig) -> None:
    export(cfg)


if __name__ == "__main__":
    main()
