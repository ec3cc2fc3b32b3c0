"""Volume rendering of packed samples: rays with different numbers of samples, flattened into one list (nerfacc style).

A batch of N rays with M samples in all is described by ``ray_indices`` (M,) (the ray each sample belongs to,
non-decreasing: a ray's samples are contiguous and ordered by distance), ``t_starts`` and ``t_ends`` (M,) (the
interval each sample stands for). Sums over a ray's samples are segment sums, done with ``index_add``; the weights
are :mod:`nerf_lightning.rendering.compositing`'s (which also holds :func:`exclusive_sum_packed`).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import torch

from nerf_lightning.rendering.compositing import exclusive_sum_packed, weights_from_optical_depth, weights_from_optical_depth_packed

__all__ = ["FixedShapeSamples", "RaySamples", "composite_on_table", "composite_packed", "exclusive_sum_packed", "on_table"]


@dataclass
class RaySamples:
    """M packed samples of N rays (see the module's docstring).

    Attributes:
        ray_indices: (M,) long, non-decreasing.
        t_starts, t_ends: (M,) each sample's interval along its ray, in the sampling space's t.
        n_rays: N.
        extras: what the sampler computed on the way and hands to its own :meth:`RaySampler.losses` (e.g. the coarse
            network's colours (N, 3)), kept out of the renderer.
        slots, width: for samples laid out on a table (a sampler's of a fixed count a ray, :meth:`from_edges`;
            :class:`FixedShapeSamples`): each sample's column (M,) in an (N + 1, width) table of the rays' steps, whose
            last row holds padding (samples of zero width, ray index N, that add nothing); None for samples of any count.
        complete: (N,) bool, the rays that kept all their samples (a loss leaves the others out); None: every ray did.
        rays_that_fit: 0-d, how many rays of what these rays wanted a sampler's fixed number of samples a step would
            hold (what :class:`~nerf_lightning.models.ray_budget.RayBudget` sizes later steps by); None without one.
    """

    ray_indices: torch.Tensor
    t_starts: torch.Tensor
    t_ends: torch.Tensor
    n_rays: int
    extras: dict[str, Any] = field(default_factory=dict)
    slots: torch.Tensor | None = None
    width: int | None = None
    complete: torch.Tensor | None = None
    rays_that_fit: torch.Tensor | None = None

    def __len__(self) -> int:
        return int(self.ray_indices.shape[0])

    @classmethod
    def from_edges(cls, edges: torch.Tensor, **extras: Any) -> RaySamples:
        """(N, S + 1) sorted interval edges of every ray -> the N x S intervals, packed."""
        n_rays, n_samples = edges.shape[0], edges.shape[1] - 1
        ray_indices = torch.arange(n_rays, device=edges.device).repeat_interleave(n_samples, output_size=n_rays * n_samples)
        slots = torch.arange(n_samples, device=edges.device).repeat(n_rays)
        return cls(ray_indices, edges[:, :-1].reshape(-1), edges[:, 1:].reshape(-1), n_rays, dict(extras), slots, n_samples)


@dataclass
class FixedShapeSamples(RaySamples):
    """Samples of a fixed count whatever the rays (a training step of fixed shapes,
    :class:`~nerf_lightning.rendering.samplers.fixed_shape_grid.FixedShapeGridSampler`'s): M is the sampler's number,
    the occupied steps first and padding of zero width (ray index N) after them, laid out on a table (``slots``,
    ``width``), with ``complete`` and ``rays_that_fit``. Every renderer composites them in one pass over the table
    (:func:`composite_on_table`): a pass whose sizes depend on the data would make the host wait for the device."""

    def __post_init__(self) -> None:
        if self.slots is None or self.width is None or self.complete is None or self.rays_that_fit is None:
            raise ValueError("FixedShapeSamples need slots, width, complete and rays_that_fit")


def on_table(values: torch.Tensor, cells: torch.Tensor, n_rays: int, width: int) -> torch.Tensor:
    """(M, ...) values of samples on a table (:attr:`RaySamples.slots`; ``cells`` (M,) their places, ray * width + slot)
    -> the (N + 1, width, ...) table, zeros where no sample is, the padding's in row N."""
    table = values.new_zeros((n_rays + 1) * width, *values.shape[1:]).index_put((cells,), values)
    return table.view(n_rays + 1, width, *values.shape[1:])


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
            see :class:`~nerf_lightning.rendering.rounds.RoundsRenderer`); None for 1.

    Returns:
        ``rgb`` (N, 3), ``depth`` (N,) (expected distance of the interval midpoints, given that the ray ends),
        ``accumulation`` (N,), ``weights`` (M,). Rays without samples get the background, accumulation 0.
    """
    dtype = torch.promote_types(rgb.dtype, torch.float32)  # half colours or densities (mixed precision) composite in float32
    rgb, density = rgb.to(dtype), density.to(dtype)
    optical_depth = density * (t_ends - t_starts).to(dtype)
    weights = weights_from_optical_depth_packed(optical_depth, ray_indices, n_rays, transmittance_before).weights
    accumulation = rgb.new_zeros(n_rays).index_add(0, ray_indices, weights)
    colour = rgb.new_zeros(n_rays, 3).index_add(0, ray_indices, weights[:, None] * rgb)
    if background is not None:
        colour = colour + (1.0 - accumulation)[:, None] * background.to(colour)
    depth = rgb.new_zeros(n_rays).index_add(0, ray_indices, weights * 0.5 * (t_starts + t_ends)) / accumulation.clamp(min=1e-10)
    return {"rgb": colour, "depth": depth, "accumulation": accumulation, "weights": weights}


def composite_on_table(rgb: torch.Tensor, density: torch.Tensor, samples: RaySamples, background: torch.Tensor) -> dict[str, torch.Tensor]:
    """Render N rays from M samples laid out on a table (``samples.slots`` and ``width``; the table form of
    :func:`composite_packed`) in one pass of sizes that do not depend on the data: rgb (M, 3) and density (M,) of
    each sample -> ``rgb`` (N, 3) with ``background`` (3,) blended in, ``depth`` (N,), ``accumulation`` (N,),
    ``weights`` (M,). The padding's row N has zero optical depth, so zero weights: composited with the rest,
    dropped from the sums."""
    n_rays, width = samples.n_rays, samples.width
    cells = samples.ray_indices * width + samples.slots  # (M,) the padding's in row N
    starts, ends = samples.t_starts, samples.t_ends
    dtype = torch.promote_types(rgb.dtype, torch.float32)
    weights = weights_from_optical_depth(on_table(density.to(dtype) * (ends - starts).to(dtype), cells, n_rays, width)).weights
    rays_weights = weights[:n_rays]  # (N, width)
    accumulation = rays_weights.sum(dim=1)
    colour = (rays_weights[..., None] * on_table(rgb.to(dtype), cells, n_rays, width)[:n_rays]).sum(dim=1)
    colour = colour + (1.0 - accumulation)[:, None] * background.to(dtype)
    mids = 0.5 * (starts + ends)
    depth = (rays_weights * on_table(mids.to(dtype), cells, n_rays, width)[:n_rays]).sum(dim=1) / accumulation.clamp(min=1e-10)
    return {"rgb": colour, "depth": depth, "accumulation": accumulation, "weights": weights.reshape(-1).index_select(0, cells)}
