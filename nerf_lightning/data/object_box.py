"""The object's box from a masked capture's silhouettes, and the scene refitted to it.

A turntable or a masked walk-around shows one object; its masks say where it is in every photo. The space a field
learns (and the range its samples cover) can then be the object's box instead of the whole room the cameras stand in:
a hash grid's cells, or a NeRF's samples, are all spent on the object.

- :func:`visual_hull_box`: the box of the masks' visual hull. A grid of points over the cameras' cube is projected
  into every training view; a point is kept where it falls inside the mask of at least ``agree`` of the views it lies
  in front of, a point outside a photo's frame counting as outside its mask (an object capture keeps its object in
  frame), and not all of them (a rough mask that cuts a little off the object in one photo would cut the object). The kept
  points' box, widened by ``margin`` of its size a side and by one grid cell, is the object's box.
- :func:`fit_scene_to_box`: the similarity that centres the box on the origin and scales its longest side to 2,
  applied to every split's cameras, the true depths, the sparse points and ``world_from_capture`` (so renders and
  meshes still map back to the capture's coordinates) and near/far. The box becomes a box inside [-1, 1]^3, which a
  preset's field box (``model.field.aabb=[-1, -1, -1, 1, 1, 1]``) then holds.
"""

from __future__ import annotations

import dataclasses

import torch

from nerf_lightning.data.formats.shared import apply_similarity
from nerf_lightning.data.points import SparsePoints
from nerf_lightning.data.scene import Scene, Views

# how many views a point must lie in front of before their masks count
MIN_SEEING = 3


def visual_hull_box(views: Views, resolution: int = 96, agree: float = 0.9, margin: float = 0.1) -> torch.Tensor:
    """(6,) float32 box (xmin, ymin, zmin, xmax, ymax, zmax) in the views' world of the masks' visual hull.

    Args:
        views: posed views with masks (N, H, W) bool.
        resolution: grid points a side over the cube that holds the cameras' centres (the loaders normalise a
            capture so that its cameras lie in [-1, 1]^3, and the object lies among them).
        agree: the fraction of the views a point lies in front of whose masks must hold it.
        margin: the box widened by this fraction of its size on every side.

    Raises ValueError naming what is missing: views without masks, or masks whose hull is empty (all black, or
    masks that do not agree with the poses).
    """
    if views.masks is None:
        raise ValueError("data.object_box=visual_hull needs the capture's masks (a masks/ folder beside the images)")
    centres = views.c2w[:, :3, 3].double()
    reach = float(centres.abs().max()) * 1.05
    ticks = torch.linspace(-reach, reach, resolution, dtype=torch.float64)
    cell = float(ticks[1] - ticks[0])
    grid = torch.stack(torch.meshgrid(ticks, ticks, ticks, indexing="ij"), dim=-1).reshape(-1, 3)
    w2c = torch.linalg.inv(views.c2w.double())
    K = views.K.double()
    chunk = max(1024, 2**22 // len(views))  # points projected at once: a few hundred MB whatever the views' count
    seen = torch.zeros(len(grid), dtype=torch.int32)
    inside = torch.zeros(len(grid), dtype=torch.int32)
    for start in range(0, len(grid), chunk):
        points = grid[start:start + chunk]
        camera = points @ w2c[:, :3, :3].transpose(1, 2) + w2c[:, None, :3, 3]  # (N, P, 3)
        z = camera[..., 2]
        pixels = camera @ K.transpose(1, 2)
        u = torch.floor(pixels[..., 0] / z.clamp(min=1e-9)).long()
        v = torch.floor(pixels[..., 1] / z.clamp(min=1e-9)).long()
        in_front = z > 1e-6
        visible = in_front & (u >= 0) & (u < views.width) & (v >= 0) & (v < views.height)
        view_index = torch.arange(len(views))[:, None].expand_as(u)
        hit = torch.zeros_like(visible)
        hit[visible] = views.masks[view_index[visible], v[visible], u[visible]]
        seen[start:start + chunk] = in_front.sum(0, dtype=torch.int32)
        inside[start:start + chunk] = hit.sum(0, dtype=torch.int32)
    kept = (seen >= MIN_SEEING) & (inside >= agree * seen.double())
    if not kept.any():
        raise ValueError(f"data.object_box=visual_hull: no point lies inside the masks of {agree:.0%} of the views that see it "
                         "(masks all black, or masks that do not match the poses); train without data.object_box")
    low, high = grid[kept].min(0).values, grid[kept].max(0).values
    widen = margin * (high - low) + cell
    return torch.cat([low - widen, high + widen]).float()


def box_similarity(box: torch.Tensor) -> torch.Tensor:
    """(4, 4) float64 similarity taking the box (6,) to one centred on the origin whose longest side is 2."""
    low, high = box[:3].double(), box[3:].double()
    scale = 2.0 / float((high - low).max())
    transform = torch.eye(4, dtype=torch.float64)
    transform[:3, :3] *= scale
    transform[:3, 3] = -scale * (low + high) / 2.0
    return transform


def _moved(views: Views, transform: torch.Tensor) -> Views:
    """The views under the similarity ``transform`` (4, 4): cameras moved, true depths scaled."""
    depth = None if views.depth is None else views.depth * float(transform[0, 0])
    return dataclasses.replace(views, c2w=apply_similarity(transform, views.c2w).to(views.c2w.dtype), depth=depth)


def fit_scene_to_box(scene: Scene, box: torch.Tensor) -> tuple[Scene, torch.Tensor]:
    """The scene moved and scaled so that ``box`` (6,) is centred on the origin with its longest side 2
    (:func:`box_similarity`), and the box (6,) in the new world (inside [-1, 1]^3)."""
    transform = box_similarity(box)
    scale = float(transform[0, 0])
    splits = {name: _moved(views, transform) for name, views in scene.splits.items()}
    points = None
    if scene.points is not None:
        points = SparsePoints.mapped(scene.points.positions.double().numpy(), scene.points.colours.numpy(), transform)
    before = torch.eye(4, dtype=torch.float64) if scene.world_from_capture is None else scene.world_from_capture.double()
    fitted = torch.cat([box[:3].double() * scale + transform[:3, 3], box[3:].double() * scale + transform[:3, 3]])
    # near/far scaled as they were: every ray's range is cut to the box (SceneSpace.bounds), for any camera
    moved = dataclasses.replace(scene, splits=splits, near=scene.near * scale, far=scene.far * scale, points=points,
                                world_from_capture=(transform @ before).float())
    return moved, fitted.float()
