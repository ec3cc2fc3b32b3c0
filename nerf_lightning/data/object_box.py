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
from nerf_lightning.geometry.rays import indexed_pixel_rays, ray_aabb_intersect

# how many views a point must lie in front of before their masks count
MIN_SEEING = 3


def mask_votes(points: torch.Tensor, c2w: torch.Tensor, K: torch.Tensor, masks: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """How many views each point lies in front of, and inside how many of those views' masks it falls.

    Args:
        points: (P, 3) in the cameras' world.
        c2w: (N, 4, 4) OpenCV camera-to-world; K: (N, 3, 3) of the masks' pixels.
        masks: (N, H, W) bool, True on the object. A point outside a photo's frame counts as outside its mask (an
            object capture keeps its object in frame).
    Returns:
        seen (P,) int32, inside (P,) int32.
    """
    count, height, width = masks.shape
    w2c = torch.linalg.inv(c2w.double())
    K = K.double()
    chunk = max(1024, 2**22 // count)  # points projected at once: a few hundred MB whatever the views' count
    seen = torch.zeros(len(points), dtype=torch.int32)
    inside = torch.zeros(len(points), dtype=torch.int32)
    for start in range(0, len(points), chunk):
        part = points[start:start + chunk].double()
        camera = part @ w2c[:, :3, :3].transpose(1, 2) + w2c[:, None, :3, 3]  # (N, P, 3)
        z = camera[..., 2]
        pixels = camera @ K.transpose(1, 2)
        u = torch.floor(pixels[..., 0] / z.clamp(min=1e-9)).long()
        v = torch.floor(pixels[..., 1] / z.clamp(min=1e-9)).long()
        in_front = z > 1e-6
        visible = in_front & (u >= 0) & (u < width) & (v >= 0) & (v < height)
        view_index = torch.arange(count)[:, None].expand_as(u)
        hit = torch.zeros_like(visible)
        hit[visible] = masks[view_index[visible], v[visible], u[visible]]
        seen[start:start + chunk] = in_front.sum(0, dtype=torch.int32)
        inside[start:start + chunk] = hit.sum(0, dtype=torch.int32)
    return seen, inside


def visual_hull(c2w: torch.Tensor, K: torch.Tensor, masks: torch.Tensor, low: torch.Tensor, high: torch.Tensor,
                resolution: int = 96, agree: float = 0.9) -> torch.Tensor:
    """(R, R, R) bool, R = ``resolution``: the masks' visual hull on a grid of R points a side from ``low`` (3,) to
    ``high`` (3,) (axis order x, y, z): a point is in it where at least :data:`MIN_SEEING` views lie behind it and it
    falls inside the masks of at least ``agree`` of them (not all: a rough mask that cuts a little off the object in
    one photo would cut the object). Cameras and masks as :func:`mask_votes` takes them."""
    ticks = [torch.linspace(float(low[axis]), float(high[axis]), resolution, dtype=torch.float64) for axis in range(3)]
    grid = torch.stack(torch.meshgrid(*ticks, indexing="ij"), dim=-1).reshape(-1, 3)
    seen, inside = mask_votes(grid, c2w, K, masks)
    return ((seen >= MIN_SEEING) & (inside >= agree * seen.double())).reshape(resolution, resolution, resolution)


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
    reach = float(views.c2w[:, :3, 3].abs().max()) * 1.05
    low, high = torch.full((3,), -reach, dtype=torch.float64), torch.full((3,), reach, dtype=torch.float64)
    hull = visual_hull(views.c2w, views.K, views.masks, low, high, resolution, agree)
    if not hull.any():
        raise ValueError(f"data.object_box=visual_hull: no point lies inside the masks of {agree:.0%} of the views that see it "
                         "(masks all black, or masks that do not match the poses); train without data.object_box")
    cell = 2.0 * reach / (resolution - 1)
    occupied = torch.nonzero(hull).double() * cell - reach
    low, high = occupied.min(0).values, occupied.max(0).values
    widen = margin * (high - low) + cell
    return torch.cat([low - widen, high + widen]).float()


def silhouette_coverage(c2w: torch.Tensor, K: torch.Tensor, masks: torch.Tensor, hull: torch.Tensor, low: torch.Tensor,
                        high: torch.Tensor, rays: int = 256, generator: torch.Generator | None = None) -> torch.Tensor:
    """(N,) float64: of each view, the fraction of its mask's pixels whose rays meet the ``hull`` (:func:`visual_hull`
    on the grid from ``low`` to ``high``), from ``rays`` of its mask's pixels drawn at random.

    Where the poses are right, the hull is the object and each mask's rays all meet it: near 1, less where a mask
    is rough. Where they are wrong, the masks do not agree: the hull is a scrap, or empty, and most rays miss it. A
    view with no mask pixel gets 0."""
    count, height, width = masks.shape
    resolution = hull.shape[0]
    low, high = low.double(), high.double()
    box = torch.cat([low, high])
    cell = (high - low) / (resolution - 1)
    steps = int(torch.ceil(2.0 * (high - low).norm() / cell.min())) + 1  # half the smallest cell a step, corner to corner
    fractions = torch.linspace(0.0, 1.0, steps, dtype=torch.float64)
    c2w, K = c2w.double(), K.double()
    coverage = torch.zeros(count, dtype=torch.float64)
    for view in range(count):
        pixels = torch.nonzero(masks[view].reshape(-1)).squeeze(1)
        if len(pixels) == 0:
            continue
        drawn = pixels[torch.randint(len(pixels), (rays,), generator=generator)]
        origins, directions = indexed_pixel_rays(K, c2w, height, width, view * height * width + drawn)
        # the ray's stretch inside the grid's box, walked in steps
        enter, leave = ray_aabb_intersect(origins, directions, box)
        enter = enter.clamp(min=0.0)
        t = enter[:, None] + (leave - enter).clamp(min=0.0)[:, None] * fractions  # (rays, steps)
        points = origins[:, None] + t[..., None] * directions[:, None]
        index = torch.round((points - low) / cell).long()
        valid = ((index >= 0) & (index < resolution)).all(-1) & (leave > enter)[:, None]
        index = index.clamp(0, resolution - 1)
        met = (hull[index[..., 0], index[..., 1], index[..., 2]] & valid).any(-1)
        coverage[view] = met.double().mean()
    return coverage


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
