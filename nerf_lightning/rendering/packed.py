"""Volume rendering of packed samples: rays with different numbers of samples, flattened into one list (nerfacc style).

A batch of N rays with M samples in all is described by ``ray_indices`` (M,) (the ray each sample belongs to,
non-decreasing: a ray's samples are contiguous and ordered by distance), ``t_starts`` and ``t_ends`` (M,) (the
interval each sample stands for). Sums over a ray's samples are segment sums, done with ``index_add``.
"""

from __future__ import annotations

import torch


def exclusive_sum_packed(values: torch.Tensor, ray_indices: torch.Tensor, n_rays: int) -> torch.Tensor:
    """(M,) values -> (M,) the sum of the earlier values of the same ray (0 for a ray's first sample).

    Computed in float64 from one running sum over the whole batch, less each ray's running sum at its start,
    so that long batches do not lose precision.
    """
    values64 = values.double()
    running = torch.cumsum(values64, dim=0)
    per_ray = torch.zeros(n_rays, dtype=torch.float64, device=values.device).index_add_(0, ray_indices, values64)
    ray_start = torch.cumsum(per_ray, dim=0) - per_ray  # (N,) running sum before each ray's first sample
    return (running - values64 - ray_start[ray_indices]).to(values.dtype)


def composite_packed(
    rgb: torch.Tensor,
    density: torch.Tensor,
    t_starts: torch.Tensor,
    t_ends: torch.Tensor,
    ray_indices: torch.Tensor,
    n_rays: int,
    background: torch.Tensor | None = None,
    transmittance_before: torch.Tensor | None = None,
) -> dict[str, torch.Tensor]:
    """Render N rays from M packed samples (the packed form of :func:`~nerf_lightning.rendering.volume.composite`).

    Args:
        rgb: (M, 3) sample colours; density: (M,) >= 0; t_starts, t_ends: (M,) intervals;
        ray_indices: (M,) non-decreasing ray of each sample; n_rays: N;
        background: (3,) blended in by 1 - accumulation, None for black.
        transmittance_before: (N,) the transmittance each ray arrives with (from samples composited earlier,
            see :func:`~nerf_lightning.rendering.renderer.render_rays_marched`); None for 1.

    Returns:
        ``rgb`` (N, 3), ``depth`` (N,) (expected distance of the interval midpoints, given that the ray ends),
        ``accumulation`` (N,), ``weights`` (M,). Rays without samples get the background, accumulation 0.
    """
    optical_depth = density * (t_ends - t_starts)
    transmittance = torch.exp(-exclusive_sum_packed(optical_depth, ray_indices, n_rays))
    if transmittance_before is not None:
        transmittance = transmittance_before[ray_indices] * transmittance
    weights = transmittance * (1.0 - torch.exp(-optical_depth))
    accumulation = rgb.new_zeros(n_rays).index_add(0, ray_indices, weights)
    colour = rgb.new_zeros(n_rays, 3).index_add(0, ray_indices, weights[:, None] * rgb)
    if background is not None:
        colour = colour + (1.0 - accumulation)[:, None] * background.to(colour)
    depth = rgb.new_zeros(n_rays).index_add(0, ray_indices, weights * 0.5 * (t_starts + t_ends)) / accumulation.clamp(min=1e-10)
    return {"rgb": colour, "depth": depth, "accumulation": accumulation, "weights": weights}
