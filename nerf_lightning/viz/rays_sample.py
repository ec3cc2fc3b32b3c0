"""The rays and samples that the pictures show, drawn as training draws them."""

from __future__ import annotations

from dataclasses import dataclass

import torch

from nerf_lightning.data.scene import Scene
from nerf_lightning.geometry.cameras import camera_to_world, pixel_to_camera, pixel_to_ray
from nerf_lightning.geometry.rays import image_pixels, sample_along_rays


@dataclass
class RaySample:
    """``rays_o``, ``rays_d`` (R, 3); ``points`` (R, S, 3) stratified samples between near and far; ``camera``
    (R,) the training view of each ray."""

    rays_o: torch.Tensor
    rays_d: torch.Tensor
    points: torch.Tensor
    camera: torch.Tensor


def draw_rays(scene: Scene, n_rays: int, n_samples: int, camera: int | None = None, seed: int = 0) -> RaySample:
    """``n_rays`` random training pixels, of all training views or of view ``camera`` only, their rays and samples."""
    train = scene.train
    generator = torch.Generator().manual_seed(seed)
    pixels = image_pixels(train.height, train.width)
    if camera is None:
        cameras = torch.randint(0, len(train), (n_rays,), generator=generator)
    else:
        if not 0 <= camera < len(train):
            raise ValueError(f"camera {camera} is out of range: the scene has {len(train)} training views")
        cameras = torch.full((n_rays,), camera, dtype=torch.long)
    uv = pixels[torch.randint(0, pixels.shape[0], (n_rays,), generator=generator)]
    rays_o, rays_d = pixel_to_ray(train.K[cameras], train.c2w[cameras], uv[:, None, :])
    rays_o, rays_d = rays_o[:, 0], rays_d[:, 0]
    points, _ = sample_along_rays(rays_o, rays_d, scene.near, scene.far, n_samples, perturb=True, generator=generator)
    return RaySample(rays_o, rays_d, points, cameras)


def frustum_corners(K: torch.Tensor, c2w: torch.Tensor, height: int, width: int, depth: float) -> torch.Tensor:
    """World positions of the image corners at ``depth`` (camera z) for (N, 3, 3) K and (N, 4, 4) c2w: (N, 4, 3)."""
    corners = torch.tensor([[0.0, 0.0], [width, 0.0], [width, height], [0.0, height]]).expand(K.shape[0], 4, 2)
    return camera_to_world(c2w, pixel_to_camera(K, corners, depth))
