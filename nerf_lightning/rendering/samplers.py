"""Where along a ray to evaluate a field: stratified intervals, and importance sampling from weights."""

from __future__ import annotations

import torch

from nerf_lightning.geometry.rays import sample_along_rays


def sample_intervals(
    rays_o: torch.Tensor,
    rays_d: torch.Tensor,
    near: float,
    far: float,
    n_samples: int,
    perturb: bool,
    generator: torch.Generator | None = None,
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Stratified samples with the lengths of the intervals they stand for.

    Returns points (N, S, 3), t (N, S) and deltas (N, S): delta_i = t_{i+1} - t_i, and for the last sample
    the even spacing (far - near) / (S - 1), so that the ray's last stretch is not given infinite length.
    """
    points, t = sample_along_rays(rays_o, rays_d, near, far, n_samples, perturb, generator)
    return points, t, deltas_of(t, (far - near) / max(n_samples - 1, 1))


def deltas_of(t: torch.Tensor, last: float) -> torch.Tensor:
    """(N, S) sorted distances -> (N, S) interval lengths, the last one ``last``."""
    return torch.cat([t[..., 1:] - t[..., :-1], torch.full_like(t[..., :1], last)], dim=-1)


def sample_pdf(
    bins: torch.Tensor, weights: torch.Tensor, n_samples: int, perturb: bool, generator: torch.Generator | None = None
) -> torch.Tensor:
    """Inverse-CDF importance sampling (NeRF's hierarchical sampling).

    Args:
        bins: (N, B + 1) sorted bin edges along each ray.
        weights: (N, B) non-negative weights of the bins (need not be normalised).
        n_samples: samples to draw per ray.
        perturb: draw uniformly at random; otherwise at evenly spaced quantiles.

    Returns:
        (N, n_samples) sorted distances, distributed within each bin uniformly and across bins in
        proportion to the weights. Not differentiable (the weights are detached).
    """
    weights = weights.detach() + 1e-5  # no empty bin: keeps the CDF strictly increasing
    pdf = weights / weights.sum(dim=-1, keepdim=True)
    cdf = torch.cat([torch.zeros_like(pdf[..., :1]), torch.cumsum(pdf, dim=-1)], dim=-1)  # (N, B + 1)
    cdf[..., -1] = 1.0
    if perturb:
        u = torch.rand(*cdf.shape[:-1], n_samples, generator=generator, dtype=cdf.dtype).to(cdf.device)
    else:
        u = torch.linspace(0.0, 1.0, n_samples, dtype=cdf.dtype, device=cdf.device).expand(*cdf.shape[:-1], n_samples)
    u = u.contiguous()
    above = torch.searchsorted(cdf, u, right=True).clamp(1, cdf.shape[-1] - 1)
    below = above - 1
    cdf_below, cdf_above = torch.gather(cdf, -1, below), torch.gather(cdf, -1, above)
    bins_below, bins_above = torch.gather(bins, -1, below), torch.gather(bins, -1, above)
    fraction = (u - cdf_below) / (cdf_above - cdf_below).clamp(min=1e-10)
    return torch.sort(bins_below + fraction * (bins_above - bins_below), dim=-1).values
