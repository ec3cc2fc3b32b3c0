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


def indexed_pixel_rays(K: torch.Tensor, c2w: torch.Tensor, height: int, width: int, index: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Rays of chosen pixels of a stack of views: K (V, 3, 3), c2w (V, 4, 4), ``index`` (N,) into the views' pixels
    flattened view by view, row-major (view * H * W + row * W + column) -> rays_o, rays_d (N, 3).

    The same rays as :func:`image_rays` gives at those pixels, computed for a batch only, so that the rays of
    all training pixels never have to be held in memory."""
    view, pixel = index // (height * width), index % (height * width)
    uv = torch.stack([pixel % width, pixel // width], dim=-1).to(K.dtype) + 0.5
    rays_o, rays_d = pixel_to_ray(K[view], c2w[view], uv[:, None, :])
    return rays_o[:, 0], rays_d[:, 0]


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


def ray_aabb_intersect(rays_o: torch.Tensor, rays_d: torch.Tensor, aabb: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Slab test. (N, 3) rays and a (6,) box -> t_enter, t_exit (N,); the ray misses where t_exit < t_enter."""
    safe_d = torch.where(rays_d.abs() < 1e-12, torch.full_like(rays_d, 1e-12), rays_d)
    t0, t1 = (aabb[:3] - rays_o) / safe_d, (aabb[3:] - rays_o) / safe_d
    return torch.minimum(t0, t1).amax(dim=-1), torch.maximum(t0, t1).amin(dim=-1)


def ndc_rays(
    rays_o: torch.Tensor, rays_d: torch.Tensor, focal: float, width: int, height: int, near_plane: float = 1.0
) -> tuple[torch.Tensor, torch.Tensor]:
    """Rays of a forward-facing scene in normalised device coordinates (NeRF's ``ndc_rays``).

    The world must have the cameras looking down -z (as LLFF's recentred world). A world point (x, y, z), z < 0,
    maps to (-(2f/W) x/z, -(2f/H) y/z, 1 + 2n/z): the plane z = -n to -1 and z = -inf to +1, so the whole depth
    range to infinity fits in [-1, 1]. Each ray's origin is first moved to the plane z = -``near_plane``.

    Args:
        rays_o, rays_d: (N, 3) rays in the world.
        focal, width, height: the cameras' focal length and image size in pixels.

    Returns:
        origins and directions (N, 3) in NDC, so that t in [0, 1] runs from the near plane to infinity (the
        directions are not unit).
    """
    t = -(near_plane + rays_o[..., 2]) / rays_d[..., 2]
    rays_o = rays_o + t[..., None] * rays_d
    ox, oy, oz = rays_o.unbind(-1)
    dx, dy, dz = rays_d.unbind(-1)
    sx, sy = -2.0 * focal / width, -2.0 * focal / height
    origins = torch.stack([sx * ox / oz, sy * oy / oz, 1.0 + 2.0 * near_plane / oz], dim=-1)
    directions = torch.stack([sx * (dx / dz - ox / oz), sy * (dy / dz - oy / oz), -2.0 * near_plane / oz], dim=-1)
    return origins, directions


def ndc_to_world(points: torch.Tensor, focal: float, width: int, height: int, near_plane: float = 1.0) -> torch.Tensor:
    """The inverse of :func:`ndc_rays`'s map: (..., 3) NDC points with z < 1 -> (..., 3) world points (z < 0)."""
    x, y, z = points.unbind(-1)
    depth = 2.0 * near_plane / (z - 1.0)
    return torch.stack([-x * depth * width / (2.0 * focal), -y * depth * height / (2.0 * focal), depth], dim=-1)
