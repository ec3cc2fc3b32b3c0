"""Empty-space skipping in a training step of fixed shapes: an occupancy grid's march into a fixed number of samples
a step (Instant-NGP's sample budget), so that no size in the step depends on the data and the GPU never waits for
the host."""

from __future__ import annotations

import torch

from nerf_lightning.fields.base import Field
from nerf_lightning.geometry.space import Rays, SceneSpace
from nerf_lightning.rendering.march_fixed import march_rays_fixed
from nerf_lightning.rendering.occupancy import OccupancyGrid
from nerf_lightning.rendering.samplers.base import RaySamples
from nerf_lightning.rendering.samplers.occupancy_grid import OccupancyGridSampler


class FixedShapeGridSampler(OccupancyGridSampler):
    """The occupancy-grid sampler whose training step takes exactly ``samples_per_step`` samples
    (:class:`~nerf_lightning.rendering.packed.FixedShapeSamples`, which every renderer composites in one pass): the
    occupied steps, padded, or the first ``samples_per_step`` of them, the rays cut short left out of that step's loss
    (:func:`~nerf_lightning.rendering.march_fixed.march_rays_fixed`). Outside training it marches as
    :class:`~nerf_lightning.rendering.samplers.occupancy_grid.OccupancyGridSampler` does (every occupied step: an
    evaluation renders whole rays), and its grid refreshes draw their cells on the device
    (:meth:`OccupancyGrid.cells_on_device <nerf_lightning.rendering.occupancy.OccupancyGrid.cells_on_device>`), so
    that nothing waits for them either.

    Args:
        grid, step_size, alpha_threshold: as the occupancy-grid sampler's.
        cone_angle: 0 only (no cone marching: the steps of a ray are laid out on a table ``reach / step_size`` wide,
            ``reach`` the grid box's diagonal); there for the occupancy-grid sampler's config, which this one extends.
        samples_per_step: the samples of a training step (Instant-NGP's 2^18).
        density_pass_samples: the occupied steps a training step first takes, evaluated once without gradients so
            that those behind an opaque surface (transmittance below ``early_stop_eps``, as the rounds renderer
            stops) or below ``alpha_threshold`` are left out of the ``samples_per_step``; None: no such pass.
        early_stop_eps: that pass's transmittance threshold.
    """

    samples_on_table = True

    def __init__(self, grid: OccupancyGrid, step_size: float = 0.02, cone_angle: float = 0.0, alpha_threshold: float = 0.0,
                 samples_per_step: int = 262144, density_pass_samples: int | None = None, early_stop_eps: float = 1e-4) -> None:
        super().__init__(grid, step_size, cone_angle, alpha_threshold)
        if samples_per_step < 1 or cone_angle != 0 or (density_pass_samples is not None and density_pass_samples < samples_per_step):
            raise ValueError(f"model/sampler=fixed_shape_grid needs samples_per_step >= 1, cone_angle=0 and density_pass_samples >= "
                             f"samples_per_step or null, got {samples_per_step}, {cone_angle:g} and {density_pass_samples}")
        self.samples_per_step, self.density_pass_samples, self.early_stop_eps = samples_per_step, density_pass_samples, early_stop_eps
        low, high = grid.aabb[:3].double(), grid.aabb[3:].double()
        self.reach = float((high - low).norm())  # the longest a ray can be inside the grid's box, read once here

    def sample(self, rays: Rays, space: SceneSpace, field: Field, perturb: bool) -> RaySamples:
        if not (perturb and torch.is_grad_enabled()):  # evaluation: every occupied step of whole rays
            return super().sample(rays, space, field, perturb)
        if space.contraction is not None or space.ndc is not None:
            raise ValueError("model/sampler=fixed_shape_grid needs a scene space without contraction or NDC (its steps' reach is "
                             "the grid's box): use model/sampler=occupancy_grid")
        t_enter, t_exit = space.ray_range(rays, self.grid.aabb)
        prune = self.alpha_threshold > 0 or self.density_pass_samples is not None
        return march_rays_fixed(
            self.grid, rays.origins, rays.directions, t_enter, t_exit, self.step_size, perturb, capacity=self.samples_per_step,
            reach=self.reach, to_field=space.to_field, density_fn=field.density if prune else None,
            alpha_threshold=self.alpha_threshold, early_stop_eps=self.early_stop_eps if self.density_pass_samples is not None else 0.0,
            march_capacity=self.density_pass_samples,
        )

    def update(self, step: int, field: Field) -> None:
        self.grid.update(step, field.density, self.step_size, draw=self.grid.cells_on_device)

    def extra_repr(self) -> str:
        return (f"{super().extra_repr()}, samples_per_step={self.samples_per_step}, "
                f"density_pass_samples={self.density_pass_samples}, early_stop_eps={self.early_stop_eps:g}")
