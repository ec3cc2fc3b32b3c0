"""The occupancy-grid march of a training step of fixed shapes (``model/sampler=fixed_shape_grid``, the GPU presets):
the same occupied steps as :func:`~nerf_lightning.rendering.occupancy.march_rays` (the readable reference, which
tests hold this equal to), laid out on a table of a fixed number of samples, so that nothing in the step waits for
the device."""

from __future__ import annotations

import math
from collections.abc import Callable

import torch

from nerf_lightning.rendering.compositing import weights_from_optical_depth
from nerf_lightning.rendering.occupancy import DensityFn, OccupancyGrid, field_space_map
from nerf_lightning.rendering.packed import FixedShapeSamples, on_table


def march_rays_fixed(
    grid: OccupancyGrid,
    rays_o: torch.Tensor,
    rays_d: torch.Tensor,
    t_enter: torch.Tensor,
    t_exit: torch.Tensor,
    step_size: float,
    perturb: bool,
    *,
    capacity: int,
    reach: float,
    to_field: Callable[[torch.Tensor], torch.Tensor] | None = None,
    density_fn: DensityFn | None = None,
    alpha_threshold: float = 0.0,
    early_stop_eps: float = 0.0,
    generator: torch.Generator | None = None,
    march_capacity: int | None = None,
) -> FixedShapeSamples:
    """March (N, 3) rays from ``t_enter`` to ``t_exit`` (N,) into exactly ``capacity`` samples
    (:class:`~nerf_lightning.rendering.packed.FixedShapeSamples`): the steps are laid out ``reach / step_size`` a ray, ``reach`` the longest a ray can be
    in the sampled range (the grid box's diagonal), and the samples are the occupied steps in order, then padding of
    zero width, or, where more steps are occupied, the first ``capacity`` of them; ``complete`` (N,) bool
    says which rays kept all their steps, so a loss can leave the others out, and ``rays_that_fit`` how many
    rays of what these wanted the capacity holds. With ``density_fn`` and an ``alpha_threshold`` or
    ``early_stop_eps``, the occupied steps first fill ``march_capacity`` samples, evaluated once without gradients
    and composited along the table, and those that pass fill the ``capacity``. Steps are ``step_size`` long (no cone
    marching), shifted by one random fraction of a step per ray when ``perturb``."""
    prune = density_fn if alpha_threshold > 0.0 or early_stop_eps > 0.0 else None
    samples = _march_fixed(grid, rays_o, rays_d, t_enter, t_exit, step_size, perturb, to_field, generator,
                           march_capacity or capacity if prune is not None else capacity, reach)
    return samples if prune is None else _pruned(samples, rays_o, rays_d, to_field, prune, alpha_threshold, early_stop_eps, capacity)


def _march_fixed(grid: OccupancyGrid, rays_o: torch.Tensor, rays_d: torch.Tensor, t_enter: torch.Tensor, t_exit: torch.Tensor,
                 step_size: float, perturb: bool, to_field: Callable[[torch.Tensor], torch.Tensor] | None,
                 generator: torch.Generator | None, capacity: int, reach: float | None) -> FixedShapeSamples:
    """:func:`~nerf_lightning.rendering.occupancy.march_rays`'s occupied steps in ``capacity`` samples on an
    (N + 1, S) table of steps, S = ceil(reach / step_size)."""
    if reach is None or reach <= 0:
        raise ValueError("march_rays_fixed needs reach, the longest a ray can be in the sampled range")
    n_rays, width = rays_o.shape[0], math.ceil(reach / step_size)
    to_field = field_space_map(to_field)
    # no generator keyword without a generator: a compiled step with a symbolic ray count cannot trace one
    draw = {} if generator is None else {"generator": generator}
    shift = (torch.rand(n_rays, 1, dtype=rays_o.dtype, device=rays_o.device, **draw) if perturb
             else torch.zeros(n_rays, 1, dtype=rays_o.dtype, device=rays_o.device))
    steps = torch.arange(width, dtype=rays_o.dtype, device=rays_o.device)
    t_starts = t_enter[:, None] + (steps + shift) * step_size  # (N, S)
    t_ends = torch.minimum(t_starts + step_size, t_exit[:, None])
    midpoints = rays_o[:, None, :] + rays_d[:, None, :] * (0.5 * (t_starts + t_ends))[..., None]
    keep = (t_starts < t_exit[:, None]) & grid.occupied(to_field(midpoints))  # (N, S)
    # the kept steps' places in the table, in order, then the padding's: the first cell of the padding row N
    # (filled with -1, then N * width: a fill value is a plain int to torch.compile, which would fix the ray count)
    cells = torch.nonzero_static(keep.reshape(-1), size=capacity, fill_value=-1)[:, 0]
    cells = torch.where(cells < 0, n_rays * width, cells)
    padded = torch.zeros(1, dtype=t_starts.dtype, device=t_starts.device)
    starts, ends = torch.cat([t_starts.reshape(-1), padded]), torch.cat([t_ends.reshape(-1), padded])
    ray_indices = torch.div(cells, width, rounding_mode="floor")
    # the ray of the last sample kept lost its later steps where the buffer is full: it and the rays after are
    # incomplete; where it is not full, the last sample is padding, of ray N: every ray is whole
    cut = ray_indices[-1]
    complete = torch.arange(n_rays, device=rays_o.device) < cut
    # how many rays of the samples a ray wants (over the rays held whole: the first, a random draw of the batch) the
    # capacity holds, for the rays of later steps (callbacks.RayBudget); a device tensor, read back a step late
    fit = capacity * cut / (ray_indices < cut).sum().clamp(min=1)  # 0 where the first ray alone overflows: the fewest rays
    return FixedShapeSamples(ray_indices, starts[cells], ends[cells], n_rays, {}, cells - ray_indices * width, width,
                             complete, fit)


def _pruned(samples: FixedShapeSamples, rays_o: torch.Tensor, rays_d: torch.Tensor, to_field: Callable[[torch.Tensor], torch.Tensor] | None,
            density_fn: DensityFn, alpha_threshold: float, early_stop_eps: float, capacity: int) -> FixedShapeSamples:
    """The fixed-capacity ``samples`` with opacity at least ``alpha_threshold`` and transmittance at least
    ``early_stop_eps`` (one density pass without gradients, composited along the table), in ``capacity`` samples."""
    n_rays, width = samples.n_rays, samples.width
    to_field = field_space_map(to_field)
    cells = samples.ray_indices * width + samples.slots
    with torch.no_grad():
        ray_of = samples.ray_indices.clamp(max=n_rays - 1)
        mids = 0.5 * (samples.t_starts + samples.t_ends)
        density = density_fn(to_field(rays_o[ray_of] + rays_d[ray_of] * mids[:, None])).float()
        composited = weights_from_optical_depth(on_table(density * (samples.t_ends - samples.t_starts).float(), cells, n_rays, width))
        alpha = composited.alpha.reshape(-1).index_select(0, cells)
        transmittance = composited.transmittance.reshape(-1).index_select(0, cells)
        keep = (samples.t_ends > samples.t_starts) & (alpha >= alpha_threshold) & (transmittance >= early_stop_eps)
    index = torch.nonzero_static(keep, size=capacity, fill_value=len(samples))[:, 0]  # the padding: one more, zero-width
    padded = torch.cat([cells, cells.new_zeros(1) + n_rays * width])  # (not new_full: it would fix the ray count when compiled)
    starts = torch.cat([samples.t_starts, samples.t_starts.new_zeros(1)])[index]
    ends = torch.cat([samples.t_ends, samples.t_ends.new_zeros(1)])[index]
    kept_cells = padded[index]
    ray_indices = torch.div(kept_cells, width, rounding_mode="floor")
    # rays cut short: those the first buffer cut, and those whose kept samples this buffer cannot all hold
    cut = ray_indices[-1]  # as in _march_fixed: the padding's ray is N
    complete = samples.complete & (torch.arange(n_rays, device=cut.device) < cut)
    # the rays both buffers hold, of what a ray the march held whole wants of each (see _march_fixed)
    whole = samples.complete
    fit = torch.minimum(samples.rays_that_fit, capacity * whole.sum() / (keep & whole[ray_of]).sum().clamp(min=1))
    return FixedShapeSamples(ray_indices, starts, ends, n_rays, {}, kept_cells - ray_indices * width, width, complete, fit)
