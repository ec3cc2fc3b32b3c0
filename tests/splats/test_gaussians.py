"""Gaussians moved by a similarity (nerf-export's capture coordinates): the same picture from the moved camera, SH
colours turned with the frame, and the random start on the training views' rays."""

from __future__ import annotations

import math

import pytest
import torch
from kornia.geometry.conversions import axis_angle_to_rotation_matrix

from nerf_lightning.data.scene import Views
from nerf_lightning.splats.gaussians import transform_gaussians
from nerf_lightning.splats.projection import project
from nerf_lightning.splats.rasterize_pairs import rasterize_pairs
from nerf_lightning.splats.sh import rotate_sh, spherical_harmonics
from nerf_lightning.splats.start import points_seen_by_views
from tests.splats.test_rasterize_pairs import HEIGHT, WIDTH, camera


def similarity(scale: float = 0.37) -> torch.Tensor:
    matrix = torch.eye(4, dtype=torch.float64)
    rotation = axis_angle_to_rotation_matrix(torch.tensor([[0.3, -1.1, 0.6]], dtype=torch.float64))[0]
    matrix[:3, :3] = scale * rotation
    matrix[:3, 3] = torch.tensor([0.5, -2.0, 1.25])
    return matrix


def splats(n: int = 40, seed: int = 0) -> dict[str, torch.Tensor]:
    generator = torch.Generator().manual_seed(seed)
    return {"means": torch.randn(n, 3, generator=generator) * 0.8, "quats": torch.randn(n, 4, generator=generator),
            "log_scales": torch.rand(n, 3, generator=generator) * 2.0 - 3.0, "opacity_logits": torch.randn(n, generator=generator),
            "sh0": torch.randn(n, 1, 3, generator=generator) * 0.5, "shN": torch.randn(n, 15, 3, generator=generator) * 0.3}


def picture(g: dict[str, torch.Tensor], K: torch.Tensor, c2w: torch.Tensor) -> dict[str, torch.Tensor]:
    projection = project(g["means"], g["quats"], g["log_scales"], torch.sigmoid(g["opacity_logits"]), K, c2w, HEIGHT, WIDTH)
    coefficients = torch.cat([g["sh0"], g["shN"]], dim=1)[projection.ids]
    colours = spherical_harmonics(3, coefficients, g["means"][projection.ids] - c2w[:3, 3])
    return rasterize_pairs(projection, colours, HEIGHT, WIDTH, torch.tensor([0.1, 0.2, 0.3]))


def test_gaussians_moved_with_the_camera_draw_the_same_picture():
    g, matrix = splats(), similarity()
    moved = transform_gaussians(g, matrix)
    K, c2w = camera()
    scale = float(torch.linalg.det(matrix[:3, :3])) ** (1 / 3)
    moved_c2w = torch.eye(4, dtype=torch.float64)
    moved_c2w[:3, :3] = matrix[:3, :3] / scale @ c2w[:3, :3].double()
    moved_c2w[:3, 3] = matrix[:3, :3] @ c2w[:3, 3].double() + matrix[:3, 3]
    before, after = picture(g, K, c2w), picture(moved, K, moved_c2w.float())
    assert before["accumulation"].mean() > 0.2  # something is drawn
    torch.testing.assert_close(after["rgb"], before["rgb"], atol=2e-4, rtol=1e-3)
    torch.testing.assert_close(after["depth"], before["depth"] * scale, atol=2e-4, rtol=1e-3)
    torch.testing.assert_close(moved["opacity_logits"], g["opacity_logits"])
    # and back: the inverse similarity gives the Gaussians again
    back = transform_gaussians(moved, torch.linalg.inv(matrix))
    for name in ("means", "log_scales", "shN"):
        torch.testing.assert_close(back[name], g[name], atol=1e-5, rtol=1e-5)


def test_rotated_sh_seen_along_the_turned_direction_is_the_old_colour():
    g = splats(n=8)
    rotation = similarity(1.0)[:3, :3]
    turned = rotate_sh(g["shN"], rotation)
    directions = torch.randn(8, 3, generator=torch.Generator().manual_seed(1))
    old = spherical_harmonics(3, torch.cat([g["sh0"], g["shN"]], 1), directions)
    new = spherical_harmonics(3, torch.cat([g["sh0"], turned], 1), directions @ rotation.float().T)
    torch.testing.assert_close(new, old, atol=1e-5, rtol=1e-5)
    assert not torch.allclose(turned, g["shN"], atol=1e-2)


@pytest.mark.parametrize("stretch", [2.0, -1.0], ids=["stretched", "mirrored"])
def test_a_transform_that_is_not_a_similarity_is_refused(stretch):
    matrix = torch.eye(4, dtype=torch.float64)
    matrix[0, 0] = stretch
    with pytest.raises(ValueError, match="similarity"):
        transform_gaussians(splats(), matrix)


def test_random_start_points_lie_on_training_rays_in_front_of_the_camera_with_their_pixels_colours():
    K, c2w = camera()
    images = torch.rand(2, HEIGHT, WIDTH, 3)
    views = Views(K=K[None].expand(2, 3, 3), c2w=c2w[None].expand(2, 4, 4), height=HEIGHT, width=WIDTH, images=images)
    positions, colours = points_seen_by_views(views, 1.0, 3.0, 500, torch.Generator().manual_seed(0))
    in_camera = positions - c2w[:3, 3]  # the camera looks down +z from (0, 0, -4), unrotated
    assert (in_camera[:, 2] >= 1.0 - 1e-5).all() and (in_camera[:, 2] <= 3.0 + 1e-5).all()
    u = K[0, 0] * in_camera[:, 0] / in_camera[:, 2] + K[0, 2]
    v = K[1, 1] * in_camera[:, 1] / in_camera[:, 2] + K[1, 2]
    assert (u >= 0).all() and (u < WIDTH).all() and (v >= 0).all() and (v < HEIGHT).all()
    # each colour is the pixel it was drawn through, in one of the two views
    pixel = images[:, v.long(), u.long()]  # (2, 500, 3)
    assert ((pixel - colours[None]).abs().amax(-1).amin(0) < 1e-6).all()
    with pytest.raises(ValueError, match="near < far"):
        points_seen_by_views(views, 3.0, 1.0, 10, torch.Generator())
    assert math.isfinite(float(positions.sum()))
