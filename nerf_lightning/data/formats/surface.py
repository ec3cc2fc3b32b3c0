"""Distances between a mesh and the procedural scene's true surface (for checking exports)."""

from __future__ import annotations

import numpy as np
import torch

from nerf_lightning.data.formats.procedural import surface_distance
from nerf_lightning.data.scene import Views
from nerf_lightning.geometry.rays import image_rays


def visible_surface_points(views: Views) -> torch.Tensor:
    """The true surface points the views see: each pixel's ray at its true depth, (P, 3)."""
    rays_o, rays_d = image_rays(views.K.double(), views.c2w.double(), views.height, views.width)
    depth = views.depth.reshape(len(views), -1).double()
    hit = torch.isfinite(depth)
    return (rays_o + rays_d * depth.nan_to_num(posinf=0.0)[..., None])[hit]


def chamfer_to_surface(vertices: np.ndarray, views: Views, chunk: int = 4096) -> dict[str, float]:
    """Mean distance from the mesh vertices to the true surface (exact, by the signed distance), from the
    visible true surface to the nearest vertex, and their mean (the Chamfer distance), in scene units."""
    vertices_t = torch.from_numpy(np.asarray(vertices)).double()
    to_surface = float(surface_distance(vertices_t).abs().mean())
    surface = visible_surface_points(views)
    nearest = torch.cat([torch.cdist(part, vertices_t).amin(dim=1) for part in surface.split(chunk)])
    to_mesh = float(nearest.mean())
    return {"mesh_to_surface": to_surface, "surface_to_mesh": to_mesh, "chamfer": 0.5 * (to_surface + to_mesh)}
