"""Where Gaussians start when a capture has no sparse points: somewhere the training views see.

3DGS and gsplat start a capture without points from a random cube; in a capture taken from one side (forward-facing)
or all around a subject in a room, most of such a cube is never seen, or lies behind the cameras. Here every start
point lies on a training pixel's ray, at a camera depth drawn uniformly between the scene's near bound and
``far``, and takes that pixel's colour: the Gaussians start where the photos can move them, already roughly the
photos' colours.
"""

from __future__ import annotations

import torch

from nerf_lightning.data.image_stack import as_float_rgb
from nerf_lightning.data.scene import Views


def points_seen_by_views(views: Views, near: float, far: float, count: int,
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
    K, c2w = views.K[view].float(), views.c2w[view].float()
    in_camera = torch.stack([(u - K[:, 0, 2]) / K[:, 0, 0], (v - K[:, 1, 2]) / K[:, 1, 1], torch.ones_like(u)], dim=-1) * depth[:, None]
    positions = (c2w[:, :3, :3] @ in_camera[..., None])[..., 0] + c2w[:, :3, 3]
    if views.images is None:
        return positions, torch.full((count, 3), 0.5)
    colours = as_float_rgb(views.images[view, v.long().clamp(max=views.height - 1), u.long().clamp(max=views.width - 1)])
    return positions, colours
