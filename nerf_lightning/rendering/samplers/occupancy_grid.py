"""Empty-space skipping as a sampler: march rays through an occupancy grid that learns from the field (Instant-NGP)."""

from __future__ import annotations

import torch

from nerf_lightning.fields.base import Field
from nerf_lightning.geometry.space import Rays, SceneSpace
from nerf_lightning.rendering.march_fixed import march_rays_fixed
from nerf_lightning.rendering.occupancy import OccupancyGrid, march_rays
from nerf_lightning.rendering.samplers.base import RaySampler, RaySamples


class OccupancyGridSampler(RaySampler):
    """Samples only the steps of a ray that lie in occupied cells of ``grid`` (nerfacc's ``OccGridEstimator``).

    Args:
        grid: the :class:`~nerf_lightning.rendering.occupancy.OccupancyGrid`, over a box of the field space;
            refreshed from the field's density every ``grid.update_every`` steps (:meth:`update`).
        step_size: the marcher's step along sampling rays (world units, or NDC t).
        cone_angle: > 0 makes the steps grow with the distance, ``max(step_size, cone_angle * t)`` (Instant-NGP's
            cone tracing), so that an unbounded scene's far background costs few samples.
        alpha_threshold: > 0 also drops steps whose opacity is below it, at the cost of a density pass.
        capacity: samples a training step, a fixed number (a fixed-shape step, for ``model/renderer=table``:
            the occupied steps, padded, or the first ``capacity`` of them, the rays cut short left out of the loss);
            None: as many as the rays have. Not with ``cone_angle``.
        march_capacity: with ``capacity``, the occupied steps a training step first takes, evaluated once without
            gradients so that those behind an opaque surface (transmittance below ``early_stop_eps``, as the
            renderer's rounds stop) or below ``alpha_threshold`` are left out of the ``capacity``; None: no such pass.
        early_stop_eps: that pass's transmittance threshold.
    """

    def __init__(self, grid: OccupancyGrid, step_size: float = 0.02, cone_angle: float = 0.0, alpha_threshold: float = 0.0,
                 capacity: int | None = None, march_capacity: int | None = None, early_stop_eps: float = 1e-4) -> None:
        super().__init__()
        if step_size <= 0 or cone_angle < 0:
            raise ValueError(f"OccupancyGridSampler needs step_size > 0 and cone_angle >= 0, got {step_size}, {cone_angle}")
        if capacity is not None and (capacity < 1 or cone_angle > 0 or (march_capacity is not None and march_capacity < capacity)):
            raise ValueError(f"model.sampler.capacity={capacity}: a fixed capacity needs capacity >= 1, cone_angle=0 and "
                             f"march_capacity >= capacity (got {cone_angle:g} and {march_capacity})")
        self.grid = grid
        self.step_size, self.cone_angle, self.alpha_threshold = step_size, cone_angle, alpha_threshold
        self.capacity, self.march_capacity, self.early_stop_eps = capacity, march_capacity, early_stop_eps
        low, high = grid.aabb[:3].double(), grid.aabb[3:].double()
        self.reach = float((high - low).norm())  # the longest a ray can be inside the grid's box, read once here

    def sample(self, rays: Rays, space: SceneSpace, field: Field, perturb: bool) -> RaySamples:
        t_enter, t_exit = space.ray_range(rays, self.grid.aabb)
        # a fixed capacity in training, where the step is to keep the device busy; evaluation renders every step
        capacity = self.capacity if perturb and torch.is_grad_enabled() else None
        if capacity is not None and (space.contraction is not None or space.ndc is not None):
            raise ValueError("model.sampler.capacity needs a scene space without contraction or NDC (its steps' reach is the grid's box)")
        if capacity is None:  # as many samples as the rays have
            return march_rays(self.grid, rays.origins, rays.directions, t_enter, t_exit, self.step_size, perturb,
                              self.cone_angle, space.to_field, density_fn=field.density if self.alpha_threshold > 0 else None,
                              alpha_threshold=self.alpha_threshold)
        prune = self.alpha_threshold > 0 or self.march_capacity is not None
        return march_rays_fixed(
            self.grid, rays.origins, rays.directions, t_enter, t_exit, self.step_size, perturb, capacity=capacity,
            reach=self.reach, to_field=space.to_field, density_fn=field.density if prune else None,
            alpha_threshold=self.alpha_threshold, early_stop_eps=self.early_stop_eps if self.march_capacity is not None else 0.0,
            march_capacity=self.march_capacity,
        )

    def update(self, step: int, field: Field) -> None:
        # a fixed-capacity step refreshes on the device too, so that nothing waits for it there either
        self.grid.update(step, field.density, self.step_size, on_device=self.capacity is not None)

    def extra_repr(self) -> str:
        capacity = f", capacity={self.capacity}, march_capacity={self.march_capacity}" if self.capacity is not None else ""
        return f"step_size={self.step_size:g}, cone_angle={self.cone_angle:g}, alpha_threshold={self.alpha_threshold:g}{capacity}"
