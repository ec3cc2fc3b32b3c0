"""Meshes of a model with a density (:class:`~nerf_lightning.models.contract.HasDensity`): marching cubes (PyMCubes) on its density, vertex colours, floaters removed, written
with trimesh as PLY, OBJ or GLB (which browsers and 3D viewers open)."""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path

import numpy as np
import torch
import trimesh

from nerf_lightning.outputs.choices import MESH_FORMATS
from nerf_lightning.io import to_uint8, write_atomic
from nerf_lightning.models.contract import HasDensity

FORMATS = MESH_FORMATS


@torch.no_grad()
def density_grid(density_fn: Callable[[torch.Tensor], torch.Tensor], low: torch.Tensor, high: torch.Tensor, resolution: int,
                 chunk: int = 65_536, device: torch.device | str = "cpu") -> torch.Tensor:
    """Density sampled at the (resolution,) * 3 corners of a grid spanning the box [low, high]: (R, R, R) on the CPU."""
    axes = [torch.linspace(float(low[i]), float(high[i]), resolution) for i in range(3)]
    points = torch.stack(torch.meshgrid(*axes, indexing="ij"), dim=-1).reshape(-1, 3)
    values = torch.cat([density_fn(part.to(device)).float().cpu() for part in points.split(chunk)])
    return values.reshape(resolution, resolution, resolution)


def marching_cubes(grid: torch.Tensor, threshold: float, low: torch.Tensor, high: torch.Tensor) -> tuple[np.ndarray, np.ndarray]:
    """The ``threshold`` level set of a (R, R, R) grid over [low, high]: vertices (V, 3) in the box's units, faces (F, 3)."""
    import mcubes

    vertices, faces = mcubes.marching_cubes(grid.numpy().astype(np.float64), threshold)
    scale = ((high - low) / (grid.shape[0] - 1)).numpy()
    return vertices * scale + low.numpy(), faces.astype(np.int64)


def vertex_colours(colour_fn: Callable[[torch.Tensor, torch.Tensor], torch.Tensor], density_fn: Callable[[torch.Tensor], torch.Tensor],
                   vertices: np.ndarray, chunk: int = 16_384, device: torch.device | str = "cpu") -> np.ndarray:
    """Colours (V, 3) uint8 at the vertices, seen from outside: along the density's gradient (density rises into
    the surface, so the gradient points the way a ray looking at it travels).

    ``colour_fn(points, viewdirs) -> (V, 3)`` and ``density_fn(points) -> (V,)`` take the vertices' coordinates."""
    colours = []
    for part in torch.from_numpy(vertices).float().split(chunk):
        points = part.to(device).requires_grad_(True)
        with torch.enable_grad():
            gradient = torch.autograd.grad(density_fn(points).sum(), points)[0]
        direction = torch.nn.functional.normalize(gradient, dim=-1)
        with torch.no_grad():
            colours.append(colour_fn(points.detach(), direction).float().cpu())
    return to_uint8(torch.cat(colours) if colours else torch.zeros(0, 3))


def keep_pieces(mesh: trimesh.Trimesh, keep: str | int) -> trimesh.Trimesh:
    """Drop the floating pieces of a density mesh: ``keep="largest"`` keeps the connected piece with the most faces,
    ``"all"`` keeps everything, an integer n keeps the pieces of at least n faces. Vertex colours follow."""
    if keep == "all" or len(mesh.faces) == 0:
        return mesh
    labels = trimesh.graph.connected_component_labels(mesh.face_adjacency, node_count=len(mesh.faces))
    sizes = np.bincount(labels)
    if keep == "largest":
        kept = labels == int(sizes.argmax())
    else:
        kept = sizes[labels] >= int(keep)
    pieces = mesh.copy()
    pieces.update_faces(kept)
    pieces.remove_unreferenced_vertices()
    return pieces


def parse_keep(keep: str | int) -> str | int:
    """``keep`` as given on the command line: largest, all, or a number of faces; ValueError naming the key otherwise."""
    if isinstance(keep, int) and not isinstance(keep, bool) and keep >= 1:
        return keep
    text = str(keep).strip().lower()
    if text in ("largest", "all"):
        return text
    if text.isdigit() and int(text) >= 1:
        return int(text)
    raise ValueError(f"keep must be largest, all or a number of faces (>= 1), got '{keep}'")


def make_mesh(vertices: np.ndarray, faces: np.ndarray, colours: np.ndarray) -> trimesh.Trimesh:
    """A trimesh mesh with uint8 vertex colours, the vertices kept as given (no merging)."""
    alpha = np.full((len(colours), 1), 255, dtype=np.uint8)
    return trimesh.Trimesh(vertices=vertices, faces=faces, vertex_colors=np.concatenate([colours, alpha], axis=1), process=False)


def write_mesh(path: str | Path, mesh: trimesh.Trimesh) -> Path:
    """Write ``mesh`` as PLY (binary, vertex colours), OBJ (``v x y z r g b``) or GLB, by ``path``'s suffix, atomically."""
    path = Path(path)
    file_type = path.suffix.lstrip(".").lower()
    if file_type not in FORMATS:
        raise ValueError(f"mesh format must be one of {', '.join(FORMATS)}, got '{file_type}' ({path})")
    data = mesh.export(file_type=file_type, include_color=True) if file_type == "obj" else mesh.export(file_type=file_type)
    return write_atomic(path, data if isinstance(data, bytes) else data.encode())


def read_mesh(path: str | Path) -> trimesh.Trimesh:
    """A mesh written by :func:`write_mesh` (any of its formats), vertices in file order."""
    loaded = trimesh.load(Path(path), process=False, force="mesh")
    return loaded


def mesh_model(model: HasDensity, bounds=None, resolution: int = 128, threshold: float = 10.0, keep: str | int = 100,
               frame: str = "capture") -> tuple[trimesh.Trimesh, dict]:
    """A coloured mesh of a model with a density (``density_at``, ``colour_at``, ``mesh_box``) by marching cubes.

    The density is sampled on a ``resolution``^3 grid over ``bounds`` ([[x, y, z] low, [x, y, z] high] in the
    sampling space: the scene's world, or NDC) or, by default, the model's ``mesh_box()``; the ``threshold`` level set
    is coloured from outside, pieces are kept by ``keep`` (:func:`keep_pieces`) and the vertices are written in the
    capture's coordinates (``frame="capture"``) or the sampling space's (``"scene"``).
    Returns the mesh and a summary (box, counts) for the log.
    """
    if frame not in ("capture", "scene"):
        raise ValueError(f"export frame must be capture or scene, got '{frame}'")
    keep = parse_keep(keep)
    device = model.device
    if bounds is not None:
        low, high = torch.tensor(list(bounds[0]), dtype=torch.float32), torch.tensor(list(bounds[1]), dtype=torch.float32)
    else:
        low, high = model.mesh_box()
    if not bool((high > low).all()):
        raise ValueError(f"export bounds must have low < high on every axis, got {low.tolist()} and {high.tolist()}")

    grid = density_grid(model.density_at, low, high, resolution, device=device)
    vertices, faces = marching_cubes(grid, threshold, low, high)
    if len(faces) == 0:
        raise ValueError(f"no surface: the density never crosses threshold={threshold} in the box {low.tolist()}..{high.tolist()} "
                         f"(its range there is {float(grid.min()):.3g}..{float(grid.max()):.3g}); lower the threshold or move the box")
    colours = vertex_colours(model.colour_at, model.density_at, vertices, device=device)
    mesh = keep_pieces(make_mesh(vertices, faces, colours), keep)
    if frame == "capture":
        mesh.vertices = model.space.to_capture(torch.from_numpy(np.asarray(mesh.vertices))).numpy()
    info = {"faces_before_keep": int(len(faces)), "faces": int(len(mesh.faces)), "vertices": int(len(mesh.vertices)),
            "box": [low.tolist(), high.tolist()], "keep": keep, "frame": frame}
    return mesh, info
