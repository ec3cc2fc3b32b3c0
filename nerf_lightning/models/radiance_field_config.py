"""A radiance field's config as a checkpoint written before nerf-lightning 0.4 saved it, read as 0.4 builds it: the
occupancy grid's step of a fixed number of samples (``capacity``, ``march_capacity`` on the occupancy-grid sampler,
with ``model/renderer=table``) is its own sampler, ``model/sampler=fixed_shape_grid``
(:class:`~nerf_lightning.rendering.FixedShapeGridSampler`), whose samples either renderer composites in one pass; and
the ``VolumeRenderer`` of before 0.3's two renderers is the one its ``fixed_shapes`` named; a config without
``depth_loss`` (before 0.5) has it 0.
:func:`~nerf_lightning.checkpoints.load_model` asks the model's class for it (``RadianceFieldModule.upgrade_config``);
a config of 0.4 passes through with only ``depth_loss`` (0: none) added where it has none."""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

RENDERING = "nerf_lightning.rendering"
OCCUPANCY_GRID = (f"{RENDERING}.OccupancyGridSampler", f"{RENDERING}.samplers.OccupancyGridSampler",
                  f"{RENDERING}.samplers.occupancy_grid.OccupancyGridSampler")
TABLE = (f"{RENDERING}.TableRenderer", f"{RENDERING}.table.TableRenderer")


def config_before_04(model: Mapping[str, Any]) -> dict[str, Any]:
    """The model config (a plain dict, as checkpoints keep it) with the fixed-shape march of before 0.4 as the
    ``fixed_shape_grid`` sampler, the ``VolumeRenderer`` as the renderer it chose, and ``depth_loss`` 0 where absent."""
    model = dict(model)
    model.setdefault("depth_loss", 0.0)  # a run of before the depth loss trained without it
    renderer = model.get("renderer")
    if isinstance(renderer, Mapping) and renderer.get("_target_") == f"{RENDERING}.VolumeRenderer":
        renderer = dict(renderer)
        table = renderer.pop("fixed_shapes", False)
        model["renderer"] = {**renderer, "_target_": f"{RENDERING}.{'TableRenderer' if table else 'RoundsRenderer'}"}
    sampler = model.get("sampler")
    if not isinstance(sampler, Mapping) or sampler.get("_target_") not in OCCUPANCY_GRID or "capacity" not in sampler:
        return model
    sampler = dict(sampler)
    capacity, march_capacity, early_stop_eps = sampler.pop("capacity"), sampler.pop("march_capacity", None), sampler.pop("early_stop_eps", None)
    if capacity is None:  # the variable march: its keys were null
        model["sampler"] = sampler
        return model
    model["sampler"] = {**sampler, "_target_": f"{RENDERING}.FixedShapeGridSampler", "samples_per_step": capacity,
                        "density_pass_samples": march_capacity,
                        **({"early_stop_eps": early_stop_eps} if early_stop_eps is not None else {})}
    if isinstance(model.get("renderer"), Mapping) and model["renderer"].get("_target_") in TABLE:
        # the table renderer held the rounds one for what it could not lay out; the samples now say which they are
        model["renderer"] = {**model["renderer"], "_target_": f"{RENDERING}.RoundsRenderer"}
    return model
