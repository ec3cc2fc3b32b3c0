"""Empty-space skipping: an occupancy grid over the field's box and a ray marcher that only samples occupied cells.

As in nerfacc's ``OccGridEstimator``: the grid keeps, for each of R^3 cells, a running (EMA) estimate of the
opacity ``density * step_size`` the field has there, refreshed every few training steps from the field itself;
a cell is occupied where that estimate exceeds ``min(threshold, mean)``. The marcher steps along each ray at a
fixed step (or one that grows with the distance, ``cone_angle``), keeps the steps whose midpoint is in an occupied
cell and, given the field's density, can drop the steps that are nearly transparent.

The grid lives in the *field space* (see :mod:`nerf_lightning.geometry.space`): its box is a box of the points the
field sees. For an unbounded scene those are contracted, the grid covers the contraction's cube [-2, 2]^3, which
holds all of space, and the marcher maps each step's midpoint through the contraction before looking it up.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence

import torch
from torch import nn

from nerf_lightning.rendering.compositing import weights_from_optical_depth_packed
from nerf_lightning.rendering.packed import RaySamples

# points (M, 3) -> densities (M,)
DensityFn = Callable[[torch.Tensor], torch.Tensor]
# a refresh's step -> the cells it evaluates (M,) and a point in each, (M, 3) in the grid's unit cube
CellDraw = Callable[[int], tuple[torch.Tensor, torch.Tensor]]


class OccupancyGrid(nn.Module):
    """A binary occupancy grid over an axis-aligned box of the field space, kept up to date from a field's density.

    Args:
        aabb: the box, 6 numbers (xmin, ymin, zmin, xmax, ymax, zmax), in the field space (the contraction's cube
            [-2, 2]^3 for an unbounded scene).
        resolution: R, cells a side.
        update_every: refresh the grid every this many training steps.
        warmup_steps: before this step a refresh evaluates every cell and replaces the estimate; after it,
            R^3 / 4 random cells and as many random occupied ones (nerfacc's schedule) are refreshed by the EMA.
        decay: the EMA factor a refreshed cell's old estimate is multiplied by before the max with the new one.
            (nerfacc decays during warmup too; with 0.95 a cell the untrained field fills then stays occupied
            for about 14 refreshes, which on a CPU costs minutes of marching through empty space.)
        threshold: opacity (density x step size) above which a cell is occupied; lowered to the grid's mean
            opacity where that is smaller, so that a field of low density everywhere is not all empty.
        seed: cells and jitter of refresh k are drawn from ``seed + k``, so a resumed run refreshes alike.

    Buffers ``occupancy`` (R, R, R) float and ``binary`` (R, R, R) bool go into checkpoints. The grid starts
    all occupied (nothing is skipped before the first refresh).
    """

    def __init__(
        self,
        aabb: Sequence[float],
        resolution: int = 128,
        update_every: int = 16,
        warmup_steps: int = 256,
        decay: float = 0.95,
        threshold: float = 0.01,
        seed: int = 0,
    ) -> None:
        super().__init__()
        aabb = torch.as_tensor(list(aabb), dtype=torch.float32)
        if aabb.shape != (6,) or not bool((aabb[3:] > aabb[:3]).all()):
            raise ValueError(f"OccupancyGrid: aabb must be 6 numbers (xmin, ymin, zmin, xmax, ymax, zmax) with min < max, got {aabb.tolist()}")
        if resolution < 1 or update_every < 1:
            raise ValueError(f"OccupancyGrid needs resolution >= 1 and update_every >= 1, got {resolution}, {update_every}")
        self.resolution, self.update_every, self.warmup_steps = resolution, update_every, warmup_steps
        self.decay, self.threshold, self.seed = decay, threshold, seed
        self.register_buffer("aabb", aabb)
        self.register_buffer("occupancy", torch.zeros(resolution, resolution, resolution))
        self.register_buffer("binary", torch.ones(resolution, resolution, resolution, dtype=torch.bool))

    def cell_of(self, points: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """(..., 3) field-space points -> (..., 3) integer cell coordinates (clamped) and (...,) whether the point is in the box."""
        unit = (points - self.aabb[:3]) / (self.aabb[3:] - self.aabb[:3])
        inside = ((unit >= 0.0) & (unit <= 1.0)).all(dim=-1)
        return (unit * self.resolution).long().clamp(0, self.resolution - 1), inside

    def occupied(self, points: torch.Tensor) -> torch.Tensor:
        """(..., 3) field-space points -> (...,) bool: inside the box and in an occupied cell."""
        cells, inside = self.cell_of(points)
        return self.binary[cells[..., 0], cells[..., 1], cells[..., 2]] & inside

    def cell_points(self, unit: torch.Tensor) -> torch.Tensor:
        """(..., 3) coordinates in the grid's unit cube -> (..., 3) field-space points."""
        return self.aabb[:3] + unit * (self.aabb[3:] - self.aabb[:3])

    def cell_centres(self) -> torch.Tensor:
        """(R, R, R, 3) the centres of the cells, in the field space."""
        axis = (torch.arange(self.resolution, device=self.aabb.device, dtype=self.aabb.dtype) + 0.5) / self.resolution
        return self.cell_points(torch.stack(torch.meshgrid(axis, axis, axis, indexing="ij"), dim=-1))

    @torch.no_grad()
    def update(self, step: int, density_fn: DensityFn, step_size: float, chunk_size: int = 65536,
               draw: CellDraw | None = None) -> bool:
        """Refresh the grid at training ``step`` if it is due; returns whether it refreshed.

        ``density_fn``: (M, 3) field-space points -> (M,) densities, evaluated at a random point of each chosen cell.
        ``step_size``: the marcher's step, which turns density into opacity.
        ``draw``: what picks the cells a refresh evaluates and a point in each (``step`` -> (M,) cells, (M, 3) points
        in the unit cube): :meth:`cells_on_host` by default (the same cells on every device), or
        :meth:`cells_on_device`, whose refresh neither reads a value back nor copies from the host (a sampler whose
        training step waits for nothing picks it).
        """
        if step % self.update_every != 0:
            return False
        cells, unit = (self.cells_on_host if draw is None else draw)(step)
        cells, unit = cells.to(self.aabb.device), unit.to(self.aabb)
        density = self._densities(density_fn, self.cell_points(unit), chunk_size)
        occupancy, estimate = self.occupancy.view(-1), density.to(self.occupancy) * step_size
        if step < self.warmup_steps:  # every cell was just evaluated: take the new estimate as it is
            occupancy.copy_(estimate)
        else:
            occupancy[cells] = torch.maximum(occupancy[cells] * self.decay, estimate)
        # the threshold, or the mean where that is lower, compared as a tensor: no value read back
        self.binary.copy_(self.occupancy > self.occupancy.mean().clamp(max=self.threshold))
        return True

    def _coordinates(self, cells: torch.Tensor) -> torch.Tensor:
        """(M,) flat cell indices -> (M, 3) integer coordinates (x, y, z)."""
        return torch.stack([cells // self.resolution**2, cells // self.resolution % self.resolution, cells % self.resolution], dim=-1)

    def cells_on_host(self, step: int) -> tuple[torch.Tensor, torch.Tensor]:
        """The cells refresh ``step`` evaluates, (M,), and a random point in each, (M, 3) in the unit cube, drawn on
        the host from ``seed + step``: every cell in warm-up, then R^3 / 4 uniform and as many occupied ones."""
        count = self.resolution**3
        generator = torch.Generator().manual_seed(self.seed + step)
        if step < self.warmup_steps:
            cells = torch.arange(count)
        else:
            uniform = torch.randint(count, (count // 4,), generator=generator)
            occupied = self.binary.flatten().nonzero()[:, 0].cpu()
            picked = occupied[torch.randint(len(occupied), (count // 4,), generator=generator)] if len(occupied) else occupied
            cells = torch.cat([uniform, picked])
        coords = self._coordinates(cells)
        return cells, (coords + torch.rand(coords.shape, generator=generator)) / self.resolution

    def cells_on_device(self, step: int) -> tuple[torch.Tensor, torch.Tensor]:
        """As :meth:`cells_on_host`, drawn on the grid's device from ``seed + step`` (other random numbers than the
        host's) in sizes that do not depend on the grid: the occupied cells are listed by ``nonzero_static`` (padded
        to R^3) and R^3 / 4 of them picked by a random index below their count, a device tensor; an empty grid's
        picks are uniform ones again."""
        count, device = self.resolution**3, self.aabb.device
        generator = torch.Generator(device=device).manual_seed(self.seed + step)
        if step < self.warmup_steps:
            cells = torch.arange(count, device=device)
        else:
            uniform = torch.randint(count, (count // 4,), generator=generator, device=device)
            binary = self.binary.flatten()
            occupied = torch.nonzero_static(binary, size=count, fill_value=0)[:, 0]  # the occupied ones first, then padding
            n_occupied = binary.sum()
            index = (torch.rand(count // 4, generator=generator, device=device) * n_occupied).long()
            picked = occupied[torch.minimum(index, (n_occupied - 1).clamp(min=0))]
            cells = torch.cat([uniform, torch.where(n_occupied > 0, picked, uniform)])
        coords = self._coordinates(cells)
        return cells, (coords + torch.rand(coords.shape, generator=generator, device=device)) / self.resolution

    def _densities(self, density_fn: DensityFn, points: torch.Tensor, chunk_size: int) -> torch.Tensor:
        """(M,) float32 densities at (M, 3) points, outside any autocast: under bf16-mixed an untrained field's
        densities round to a few values, and a grid of equal values has no cell above its mean (an empty grid, no
        samples, no gradient: training would never start)."""
        with torch.autocast(device_type=points.device.type, enabled=False):
            return torch.cat([density_fn(part).float() for part in points.split(chunk_size)])

    def mark_from_density(self, density_fn: DensityFn, step_size: float, chunk_size: int = 65536) -> None:
        """Set the grid at once from the density at the cell centres (no EMA): for a known field or a checkpoint."""
        with torch.no_grad():
            points = self.cell_centres().reshape(-1, 3)
            density = self._densities(density_fn, points, chunk_size)
            self.occupancy.copy_((density * step_size).reshape(self.occupancy.shape))
            self.binary.copy_(self.occupancy > self.occupancy.mean().clamp(max=self.threshold))


def field_space_map(to_field: Callable[[torch.Tensor], torch.Tensor] | None) -> Callable[[torch.Tensor], torch.Tensor]:
    """A marcher's map from sampling-space points to the field space: ``to_field``, or the identity where it is None
    (a scene without contraction). Compared with None, never asked for its truth (``to_field or identity``): torch
    2.11's dynamo cannot tell the truth of a bound method and fails a fullgraph compile with "Data-dependent
    branching"."""
    return _identity if to_field is None else to_field


def _identity(points: torch.Tensor) -> torch.Tensor:
    return points


def step_edges(start: float, stop: float, step_size: float, cone_angle: float) -> torch.Tensor:
    """(K + 1,) float32 edges of the steps from ``start`` to past ``stop``: a step at distance t is
    ``max(step_size, cone_angle * t)`` long, so constant up to t = step_size / cone_angle and growing
    geometrically, by (1 + cone_angle) a step, beyond it (Instant-NGP's cone tracing). The counts are worked out in
    Python floats, the edges in float32 (no float64 tensor, which Apple GPUs lack): each edge is one product or one
    power, so its error does not grow along the ray."""
    linear_end = max(start, step_size / cone_angle)
    n_linear = math.ceil(max(min(linear_end, stop) - start, 0.0) / step_size)
    edges = start + step_size * torch.arange(n_linear + 1, dtype=torch.float32)
    last = start + step_size * n_linear
    if last < stop:
        n_geometric = math.ceil(math.log(stop / last) / math.log1p(cone_angle))
        growth = torch.tensor(1.0 + cone_angle, dtype=torch.float32) ** torch.arange(1, n_geometric + 1, dtype=torch.float32)
        edges = torch.cat([edges, last * growth])
    return edges


def march_rays(
    grid: OccupancyGrid,
    rays_o: torch.Tensor,
    rays_d: torch.Tensor,
    t_enter: torch.Tensor,
    t_exit: torch.Tensor,
    step_size: float,
    perturb: bool,
    cone_angle: float = 0.0,
    to_field: Callable[[torch.Tensor], torch.Tensor] | None = None,
    density_fn: DensityFn | None = None,
    alpha_threshold: float = 0.0,
    early_stop_eps: float = 0.0,
    generator: torch.Generator | None = None,
) -> RaySamples:
    """March (N, 3) rays from ``t_enter`` to ``t_exit`` (N,) (see :meth:`SceneSpace.ray_range
    <nerf_lightning.geometry.space.SceneSpace.ray_range>`); packed samples of the steps in occupied cells.

    Steps are ``step_size`` long from ``t_enter``, shifted by one random fraction of a step per ray when
    ``perturb``; the last is cut at ``t_exit``, so that no sample reaches beyond it. With ``cone_angle`` > 0 a step
    at distance t is ``max(step_size, cone_angle * t)`` long instead (:func:`step_edges`, the same for every ray),
    and a ray's first step is the first of them after ``t_enter``. A step is kept where its midpoint, passed
    through ``to_field`` (the scene's contraction, if any), lies in an occupied cell. With ``density_fn`` (field-space
    points -> densities) the kept steps are evaluated once without gradients, and those with opacity below
    ``alpha_threshold`` or transmittance below ``early_stop_eps`` (the ray has already ended) are dropped as well.

    A training step of fixed shapes marches with :func:`~nerf_lightning.rendering.march_fixed.march_rays_fixed`
    instead (``model/sampler=fixed_shape_grid``), which tests hold equal to this one.
    """
    n_rays = rays_o.shape[0]
    to_field = field_space_map(to_field)
    if perturb:
        shift = torch.rand(n_rays, 1, generator=generator, dtype=rays_o.dtype, device=rays_o.device)
    else:
        shift = torch.zeros(n_rays, 1, dtype=rays_o.dtype, device=rays_o.device)
    hit = t_exit > t_enter
    if cone_angle > 0.0 and bool(hit.any()):
        edges = step_edges(float(t_enter[hit].min()), float(t_exit[hit].max()), step_size, cone_angle).to(rays_o.device)
        widths = edges[1:] - edges[:-1]
        t_starts = edges[:-1] + shift * widths  # (N, K)
        t_ends = torch.minimum(edges[1:] + shift * torch.cat([widths[1:], widths[-1:]]), t_exit[:, None])
        t_starts = torch.where(t_starts >= t_enter[:, None], t_starts, t_exit[:, None])  # before the range: dropped below
    else:
        length = (t_exit - t_enter).clamp(min=0.0)
        n_steps = int(math.ceil(float(length.max()) / step_size)) if n_rays else 0
        steps = torch.arange(n_steps, dtype=rays_o.dtype, device=rays_o.device)
        t_starts = t_enter[:, None] + (steps + shift) * step_size  # (N, n_steps)
        t_ends = torch.minimum(t_starts + step_size, t_exit[:, None])
    midpoints = rays_o[:, None, :] + rays_d[:, None, :] * (0.5 * (t_starts + t_ends))[..., None]
    keep = (t_starts < t_exit[:, None]) & grid.occupied(to_field(midpoints))
    ray_indices = keep.nonzero()[:, 0]  # row-major: by ray, then by distance
    samples = RaySamples(ray_indices, t_starts[keep], t_ends[keep], n_rays)
    if density_fn is None or (alpha_threshold <= 0.0 and early_stop_eps <= 0.0) or len(samples) == 0:
        return samples
    with torch.no_grad():
        t_mid = 0.5 * (samples.t_starts + samples.t_ends)
        density = density_fn(to_field(rays_o[ray_indices] + rays_d[ray_indices] * t_mid[:, None]))
        composited = weights_from_optical_depth_packed(density * (samples.t_ends - samples.t_starts), ray_indices, n_rays)
        keep = (composited.alpha >= alpha_threshold) & (composited.transmittance >= early_stop_eps)
    return RaySamples(ray_indices[keep], samples.t_starts[keep], samples.t_ends[keep], n_rays)
