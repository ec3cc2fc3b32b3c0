"""Where Gaussians start when a capture has no sparse points: somewhere the training views see.

3DGS and gsplat start a capture without points from a random cube; in a capture taken from one side (forward-facing)
or all around a subject in a room, most of such a cube is never seen, or lies behind the cameras. Here every start
point lies on a training pixel's ray, at a camera depth drawn uniformly between the scene's near bound and
``far``, and takes that pixel's colour: the Gaussians start where the photos can move them, already roughly the
photos' colours.

With masks that cut the object out (``data.masks=background``) the start is the masks' visual hull
(:func:`points_in_visual_hull`): points on the masked pixels' rays that every other view which sees them also
sees inside its mask, so that the Gaussians start on the object, not in the black around it.

The views come in as the Scene's ``Views`` hold them (any object with their fields: :class:`PosedViews`); which start
a model takes, and from which scene, is the models' business (:mod:`~nerf_lightning.models.splat_start`).
"""

from __future__ import annotations

from typing import Protocol

import torch

from nerf_lightning.splats.projection import frame_positions


class PosedViews(Protocol):
    """What a start reads of the training views (a Scene's ``Views`` has it): K (V, 3, 3), OpenCV c2w (V, 4, 4), the
    size, images (V, H, W, 3) uint8 or float in [0, 1] or None, masks (V, H, W) bool or None."""

    K: torch.Tensor
    c2w: torch.Tensor
    height: int
    width: int
    images: torch.Tensor | None
    masks: torch.Tensor | None

    def __len__(self) -> int: ...


def points_seen_by_views(views: PosedViews, near: float, far: float, count: int,
                         generator: torch.Generator) -> tuple[torch.Tensor, torch.Tensor]:
    """``count`` points on random training pixels' rays at camera depths uniform in [near, far] -> positions
    (count, 3) in the views' world and colours (count, 3) in [0, 1] (each its pixel's; grey where the views have
    no images)."""
    if not 0 <= near < far:
        raise ValueError(f"random start points need 0 <= near < far, got near={near}, far={far}")
    view = torch.randint(len(views), (count,), generator=generator)
    u = torch.rand(count, generator=generator) * views.width
    v = torch.rand(count, generator=generator) * views.height
    depth = near + (far - near) * torch.rand(count, generator=generator)
    return points_at_pixels(views, view, u, v, depth), colours_at_pixels(views, view, u, v)


def points_at_pixels(views: PosedViews, view: torch.Tensor, u: torch.Tensor, v: torch.Tensor, depth: torch.Tensor) -> torch.Tensor:
    """(P,) view indices, pixel coordinates u, v and camera depths -> (P, 3) points on those pixels' rays in the world."""
    K, c2w = views.K[view].float(), views.c2w[view].float()
    in_camera = torch.stack([(u - K[:, 0, 2]) / K[:, 0, 0], (v - K[:, 1, 2]) / K[:, 1, 1], torch.ones_like(u)], dim=-1) * depth[:, None]
    return (c2w[:, :3, :3] @ in_camera[..., None])[..., 0] + c2w[:, :3, 3]


def colours_at_pixels(views: PosedViews, view: torch.Tensor, u: torch.Tensor, v: torch.Tensor) -> torch.Tensor:
    """(P, 3) the colours of those pixels in [0, 1] (grey where the views have no images)."""
    if views.images is None:
        return torch.full((len(view), 3), 0.5)
    colours = views.images[view, v.long().clamp(max=views.height - 1), u.long().clamp(max=views.width - 1)]
    return colours.to(torch.float32) / 255.0 if colours.dtype == torch.uint8 else colours


def points_in_visual_hull(views: PosedViews, near: float, far: float, count: int, generator: torch.Generator,
                          agreement: float = 0.9, min_seen: float = 0.25, tries: int = 16) -> tuple[torch.Tensor, torch.Tensor]:
    """``count`` points inside the visual hull of the training views' masks -> positions (count, 3) and colours
    (count, 3) in [0, 1]: candidates on random masked pixels' rays (depths uniform in [near, far]), kept where at least
    ``agreement`` of the views that see them in frame see them inside their masks (a rough hand-made mask misses
    some views), and at least ``min_seen`` of the views (and 3) see them in frame. Candidates are drawn ``tries``
    times as many as wanted; fewer than ``count`` come back where fewer were kept. ValueError where none is kept
    (masks that do not agree: wrong poses, or masks of another object)."""
    if views.masks is None:
        raise ValueError("a visual hull start needs the training views' masks")
    masks = views.masks.reshape(len(views), -1)
    pixels = torch.nonzero(masks.reshape(-1)).squeeze(1)
    if len(pixels) == 0:
        raise ValueError("the training views' masks cover no pixel: no visual hull to start the Gaussians in")
    drawn = pixels[torch.randint(len(pixels), (tries * count,), generator=generator)]
    view, pixel = drawn // masks.shape[1], drawn % masks.shape[1]
    v = (pixel // views.width).float() + torch.rand(len(drawn), generator=generator)
    u = (pixel % views.width).float() + torch.rand(len(drawn), generator=generator)
    depth = near + (far - near) * torch.rand(len(drawn), generator=generator)
    positions = points_at_pixels(views, view, u, v, depth)
    K, c2w = views.K.float(), views.c2w.float()
    inside = torch.zeros(len(drawn))
    seen = torch.zeros(len(drawn))
    for other in range(len(views)):  # project every candidate into each view: in frame? inside the mask?
        [column], [row], [in_frame] = frame_positions(positions, K[other:other + 1], c2w[other:other + 1], views.height,
                                                      views.width, near=1e-6)
        index = row.long().clamp(0, views.height - 1) * views.width + column.long().clamp(0, views.width - 1)
        seen += in_frame.float()
        inside += (in_frame & masks[other][index]).float()
    # and seen by enough views: a point off to the side, in frame of its own view alone, is inside that one mask
    enough = max(3.0, min_seen * len(views))
    kept = torch.nonzero((inside >= agreement * seen) & (seen >= enough)).squeeze(1)
    if len(kept) == 0:
        raise ValueError("no point on the masked pixels' rays lies inside the other views' masks: the masks and the poses "
                         "do not agree (masks of another photo, or poses of another capture)")
    kept = kept[:count]  # fewer where few candidates were kept: a repeated point would start with no size
    return positions[kept], colours_at_pixels(views, view[kept], u[kept], v[kept])
