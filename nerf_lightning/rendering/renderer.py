"""Rendering rays through a field: stratified samples, optional hierarchical samples, compositing."""

from __future__ import annotations

from collections.abc import Callable

import torch

from nerf_lightning.rendering.occupancy import OccupancyGrid, march_rays
from nerf_lightning.rendering.packed import composite_packed
from nerf_lightning.rendering.samplers import deltas_of, sample_intervals, sample_pdf
from nerf_lightning.rendering.volume import composite

# a field: (points (N, S, 3), directions (N, S, 3)) -> {"rgb": (N, S, 3), "density": (N, S)}
Field = Callable[[torch.Tensor, torch.Tensor], dict[str, torch.Tensor]]


def _query(field: Field, rays_o, rays_d, t, deltas, background, directions):
    points = rays_o[:, None, :] + rays_d[:, None, :] * t[..., None]
    out = field(points, directions[:, None, :].expand_as(points))
    return composite(out["rgb"], out["density"], t, deltas, background)


def render_rays(
    field: Field,
    rays_o: torch.Tensor,
    rays_d: torch.Tensor,
    near: float,
    far: float,
    n_samples: int,
    perturb: bool,
    background: torch.Tensor | None = None,
    fine_field: Field | None = None,
    n_fine_samples: int = 0,
    generator: torch.Generator | None = None,
    directions: torch.Tensor | None = None,
) -> dict[str, torch.Tensor]:
    """Render (N, 3) rays with unit directions.

    ``directions``: (N, 3) unit view directions the field sees, where they differ from ``rays_d`` (NDC rays).

    ``n_samples`` stratified samples between near and far go through ``field``. With a ``fine_field`` and
    ``n_fine_samples`` > 0 (NeRF's hierarchical sampling), that many more samples are drawn from the coarse
    weights by inverse-CDF sampling and the fine field renders the union of both sets; the coarse result is
    returned too, under ``coarse_*`` keys, for its own loss.

    Returns ``rgb`` (N, 3), ``depth`` (N,), ``accumulation`` (N,), ``weights`` (N, S), ``t`` (N, S).
    """
    directions = rays_d if directions is None else directions
    _, t, deltas = sample_intervals(rays_o, rays_d, near, far, n_samples, perturb, generator)
    coarse = _query(field, rays_o, rays_d, t, deltas, background, directions)
    coarse["t"] = t
    if fine_field is None or n_fine_samples <= 0:
        return coarse
    mids = 0.5 * (t[:, 1:] + t[:, :-1])  # bin edges between the coarse samples
    t_fine = sample_pdf(mids, coarse["weights"][:, 1:-1], n_fine_samples, perturb, generator)
    t_all = torch.sort(torch.cat([t, t_fine], dim=-1), dim=-1).values
    fine = _query(fine_field, rays_o, rays_d, t_all, deltas_of(t_all, (far - near) / max(n_samples - 1, 1)), background, directions)
    fine["t"] = t_all
    fine.update({f"coarse_{key}": value for key, value in coarse.items() if key in ("rgb", "depth", "accumulation")})
    return fine


def render_rays_marched(
    field: Field,
    grid: OccupancyGrid,
    rays_o: torch.Tensor,
    rays_d: torch.Tensor,
    near: float,
    far: float,
    step_size: float,
    perturb: bool,
    background: torch.Tensor | None = None,
    alpha_threshold: float = 0.0,
    early_stop_eps: float = 1e-4,
    samples_per_round: int = 16,
    generator: torch.Generator | None = None,
    directions: torch.Tensor | None = None,
    cone_angle: float = 0.0,
) -> dict[str, torch.Tensor]:
    """Render (N, 3) rays with unit directions through the occupied cells of ``grid`` only (empty-space skipping).

    The marcher (:func:`~nerf_lightning.rendering.occupancy.march_rays`) lists the steps in occupied cells;
    the field is then evaluated in rounds, the next ``samples_per_round`` of each ray at a time, and a ray
    leaves once its transmittance is below ``early_stop_eps``, so the samples behind an opaque surface are
    never evaluated (on a CPU this is most of the saving; no extra density pass is needed). With
    ``early_stop_eps=0`` the result equals compositing every listed sample. ``alpha_threshold`` > 0 also
    drops nearly transparent steps, at the cost of a density pass (``field.density``) in the marcher.

    ``directions``: (N, 3) unit view directions the field sees, where they differ from ``rays_d`` (NDC rays).
    ``cone_angle`` > 0: steps grow with the distance (see :func:`~nerf_lightning.rendering.occupancy.march_rays`).

    Returns ``rgb`` (N, 3), ``depth`` (N,), ``accumulation`` (N,) and ``n_samples`` (how many samples the
    field was evaluated at, a 0-d tensor).
    """
    n_rays = rays_o.shape[0]
    directions = rays_d if directions is None else directions
    ray_indices, t_starts, t_ends = march_rays(
        grid, rays_o, rays_d, near, far, step_size, perturb, generator,
        density_fn=field.density if alpha_threshold > 0 else None, alpha_threshold=alpha_threshold, cone_angle=cone_angle,
    )
    counts = torch.bincount(ray_indices, minlength=n_rays)
    rank = torch.arange(len(ray_indices), device=rays_o.device) - (torch.cumsum(counts, 0) - counts)[ray_indices]  # (M,) within its ray
    transmittance = rays_o.new_ones(n_rays)
    colour, accumulation, depth_sum = rays_o.new_zeros(n_rays, 3), rays_o.new_zeros(n_rays), rays_o.new_zeros(n_rays)
    evaluated = 0
    for first in range(0, int(counts.max()) if len(counts) else 0, samples_per_round):
        alive = transmittance.detach() >= early_stop_eps
        chosen = (rank >= first) & (rank < first + samples_per_round) & alive[ray_indices]
        if not chosen.any():
            break
        indices, starts, ends = ray_indices[chosen], t_starts[chosen], t_ends[chosen]
        points = rays_o[indices] + rays_d[indices] * (0.5 * (starts + ends))[:, None]
        out = field(points, directions[indices])
        part = composite_packed(out["rgb"], out["density"], starts, ends, indices, n_rays, transmittance_before=transmittance)
        colour, accumulation = colour + part["rgb"], accumulation + part["accumulation"]
        depth_sum = depth_sum + part["depth"] * part["accumulation"]
        transmittance = transmittance - part["accumulation"]
        evaluated += len(indices)
    if background is not None:
        colour = colour + (1.0 - accumulation)[:, None] * background.to(colour)
    depth = depth_sum / accumulation.clamp(min=1e-10)
    return {"rgb": colour, "depth": depth, "accumulation": accumulation, "n_samples": torch.tensor(evaluated, device=rays_o.device)}
