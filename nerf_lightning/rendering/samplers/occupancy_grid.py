"""Empty-space skipping as a sampler: march rays through an occupancy grid that learns from the field (Instant-NGP)."""

from __future__ import annotations

from nerf_lightning.fields.base import Field
from nerf_lightning.geometry.space import Rays, SceneSpace
from nerf_lightning.rendering.occupancy import OccupancyGrid, march_rays
from nerf_lightning.rendering.samplers.base import RaySampler, RaySamples

# what a config of before 0.4 holding a capacity is told (its keys: model.sampler.capacity, march_capacity)
FIXED_SHAPES_MOVED = ("model.sampler.capacity={capacity}: a training step of a fixed number of samples is its own sampler "
                      "since nerf-lightning 0.4: use model/sampler=fixed_shape_grid with model.sampler.samples_per_step="
                      "{capacity} (and model.sampler.density_pass_samples for march_capacity)")


class OccupancyGridSampler(RaySampler):
    """Samples only the steps of a ray that lie in occupied cells of ``grid`` (nerfacc's ``OccGridEstimator``), as
    many as the rays have (a training step of a fixed number:
    :class:`~nerf_lightning.rendering.samplers.fixed_shape_grid.FixedShapeGridSampler`).

    Args:
        grid: the :class:`~nerf_lightning.rendering.occupancy.OccupancyGrid`, over a box of the field space;
            refreshed from the field's density every ``grid.update_every`` steps (:meth:`update`).
        step_size: the marcher's step along sampling rays (world units, or NDC t).
        cone_angle: > 0 makes the steps grow with the distance, ``max(step_size, cone_angle * t)`` (Instant-NGP's
            cone tracing), so that an unbounded scene's far background costs few samples.
        alpha_threshold: > 0 also drops steps whose opacity is below it, at the cost of a density pass.
        capacity, march_capacity, early_stop_eps: the keys of configs and checkpoints of before 0.4, where they were
            null; a capacity is answered in one line naming ``model/sampler=fixed_shape_grid``.
    """

    samples_on_table = False

    def __init__(self, grid: OccupancyGrid, step_size: float = 0.02, cone_angle: float = 0.0, alpha_threshold: float = 0.0,
                 *, capacity: None = None, march_capacity: None = None, early_stop_eps: float | None = None) -> None:
        super().__init__()
        if capacity is not None or march_capacity is not None:
            raise ValueError(FIXED_SHAPES_MOVED.format(capacity=capacity))
        if step_size <= 0 or cone_angle < 0:
            raise ValueError(f"OccupancyGridSampler needs step_size > 0 and cone_angle >= 0, got {step_size}, {cone_angle}")
        self.grid = grid
        self.step_size, self.cone_angle, self.alpha_threshold = step_size, cone_angle, alpha_threshold

    def sample(self, rays: Rays, space: SceneSpace, field: Field, perturb: bool) -> RaySamples:
        t_enter, t_exit = space.ray_range(rays, self.grid.aabb)
        return march_rays(self.grid, rays.origins, rays.directions, t_enter, t_exit, self.step_size, perturb,
                          self.cone_angle, space.to_field, density_fn=field.density if self.alpha_threshold > 0 else None,
                          alpha_threshold=self.alpha_threshold)

    def update(self, step: int, field: Field) -> None:
        self.grid.update(step, field.density, self.step_size)

    def extra_repr(self) -> str:
        return f"step_size={self.step_size:g}, cone_angle={self.cone_angle:g}, alpha_threshold={self.alpha_threshold:g}"
