"""Where Gaussians start without sparse points: on training pixels' rays, and with masks that cut the object out,
inside the masks' visual hull."""

from __future__ import annotations

import math

import pytest
import torch

from nerf_lightning.data.scene import Views
from nerf_lightning.geometry.cameras import look_at
from nerf_lightning.splats.start import points_in_visual_hull, points_seen_by_views

RADIUS = 0.3  # a ball at the origin, the object the masks cut out


def ring_of_views(count: int = 12, size: int = 64, distance: float = 3.0) -> Views:
    """Cameras on a ring round the origin, each mask the ball's outline, each image red on the ball and blue off it."""
    angles = torch.arange(count) * 2 * math.pi / count
    eyes = torch.stack([distance * torch.cos(angles), distance * torch.sin(angles), 0.8 * torch.ones(count)], dim=-1)
    c2w = look_at(eyes)
    focal = size * 1.5
    K = torch.tensor([[focal, 0.0, size / 2], [0.0, focal, size / 2], [0.0, 0.0, 1.0]]).expand(count, 3, 3).clone()
    v, u = torch.meshgrid(torch.arange(size) + 0.5, torch.arange(size) + 0.5, indexing="ij")
    directions = torch.stack([(u - size / 2) / focal, (v - size / 2) / focal, torch.ones_like(u)], dim=-1)
    masks = []
    for camera in c2w:  # a pixel is on the ball where its ray passes within RADIUS of the origin
        rays = torch.nn.functional.normalize(directions @ camera[:3, :3].T, dim=-1)
        along = -(camera[:3, 3] * rays).sum(-1)
        closest = camera[:3, 3] + along[..., None] * rays
        masks.append(closest.norm(dim=-1) < RADIUS)
    masks = torch.stack(masks)
    images = torch.where(masks[..., None], torch.tensor([1.0, 0.0, 0.0]), torch.tensor([0.0, 0.0, 1.0]))
    return Views(K=K, c2w=c2w, height=size, width=size, images=images, masks=masks)


def test_the_visual_hull_start_lies_on_the_object_and_takes_its_colour():
    views = ring_of_views()
    positions, colours = points_in_visual_hull(views, 0.5, 6.0, 2000, torch.Generator().manual_seed(0))
    assert len(positions) == 2000
    # a ring of 12 views carves the ball's hull a little larger than the ball, far from the 3-unit cameras
    assert positions.norm(dim=-1).max() < 1.6 * RADIUS
    torch.testing.assert_close(colours, torch.tensor([1.0, 0.0, 0.0]).expand(2000, 3))
    # the rays' start, for comparison, spreads along the whole depth range
    spread, _ = points_seen_by_views(views, 0.5, 6.0, 2000, torch.Generator().manual_seed(0))
    assert (spread.norm(dim=-1) > 1.6 * RADIUS).float().mean() > 0.5


def test_masks_that_do_not_agree_with_the_poses_are_refused_in_one_line():
    views = ring_of_views()
    views.masks[:, :, : views.width // 2] = False  # the ball's left half cut from every mask,
    views.masks[1::2] = torch.flip(views.masks[1::2], dims=[2])  # and every other view's right half: nothing left in common
    with pytest.raises(ValueError, match="the masks and the poses do not agree"):
        points_in_visual_hull(views, 0.5, 6.0, 500, torch.Generator().manual_seed(0))


def test_nothing_below_the_models_reads_the_formats_or_the_capture_tools():
    """The start's geometry takes the views it is given; which start, from which scene, the models choose
    (models/splat_start.py): no module of the layers below the models imports data/ or capture/."""
    from tests.test_layers import graph

    below = ("geometry", "fields", "rendering", "splats", "parameters")
    reads = [f"{module} imports {target}" for module, targets in graph().items()
             if module.split(".")[1:2] and module.split(".")[1] in below
             for target in sorted(targets) if target.split(".")[1:2] and target.split(".")[1] in ("data", "capture")]
    assert not reads, "\n".join(reads)
