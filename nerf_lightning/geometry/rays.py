"""Rays of whole images, and samples along rays."""

from __future__ import annotations

import torch
from kornia.utils import create_meshgrid

from nerf_lightning.geometry.cameras import pixel_to_ray


def image_pixels(height: int, width: int, device: torch.device | str | None = None) -> torch.Tensor:
    """Pixel centres (u, v) = (j + 0.5, i + 0.5) of an image, row-major: (H * W, 2)."""
    grid = create_meshgrid(height, width, normalized_coordinates=False, device=device)  # (1, H, W, 2) as (x, y)
    return grid.reshape(-1, 2) + 0.5


def image_rays(K: torch.Tensor, c2w: torch.Tensor, height: int, width: int) -> tuple[torch.Tensor, torch.Tensor]:
    """Rays of every pixel of every view: K (B, 3, 3), c2w (B, 4, 4) -> rays_o, rays_d (B, H * W, 3), row-major."""
    uv = image_pixels(height, width, device=K.device).to(K.dtype).expand(K.shape[0], -1, -1)
    return pixel_to_ray(K, c2w, uv)


def sample_along_rays(
    rays_o: torch.Tensor,
    rays_d: torch.Tensor,
    near: float | torch.Tensor,
    far: float | torch.Tensor,
    n_samples: int,
    perturb: bool,
    generator: torch.Generator | None = None,
) -> tuple[torch.Tensor, torch.Tensor]:
    """Stratified samples between near and far: rays (N, 3) -> points (N, S, 3) and distances t (N, S).

    In evaluation (``perturb=False``) t is evenly spaced from near to far, both included. In training
    each t is drawn uniformly inside its stratum, the interval between the midpoints around the even
    position (NeRF's stratified sampling), so that over many steps the field is queried everywhere.
    ``near`` and ``far`` are numbers or (N, 1) tensors; t is in units of ``rays_d``'s length.
    """
    steps = torch.linspace(0.0, 1.0, n_samples, device=rays_o.device, dtype=rays_o.dtype)
    near = torch.as_tensor(near, device=rays_o.device, dtype=rays_o.dtype)
    far = torch.as_tensor(far, device=rays_o.device, dtype=rays_o.dtype)
    t = (near * (1.0 - steps) + far * steps).expand(rays_o.shape[0], n_samples)
    if perturb:
        mids = 0.5 * (t[:, 1:] + t[:, :-1])
        upper = torch.cat([mids, t[:, -1:]], dim=-1)
        lower = torch.cat([t[:, :1], mids], dim=-1)
        u = torch.rand(t.shape, generator=generator, device=t.device if generator is None else generator.device, dtype=t.dtype)
        t = lower + (upper - lower) * u.to(t.device)
    points = rays_o[:, None, :] + rays_d[:, None, :] * t[..., None]
    return points, t.contiguous()
