"""What a radiance field is to the samplers and the renderer: a typed protocol, not a base class."""

from __future__ import annotations

from typing import Protocol, runtime_checkable

import torch


@runtime_checkable
class Field(Protocol):
    """A radiance field over the *field space* (see :mod:`nerf_lightning.geometry.space`).

    ``field(points, viewdirs)``: points (..., 3) and unit view directions (..., 3) -> ``{"rgb": (..., 3) in [0, 1],
    "density": (...,) >= 0}``, differentiable. ``field.density(points)``: (..., 3) -> (...,) densities, what
    occupancy grids, proposal samplers' checks and meshes query without a direction.

    ``aabb``: (6,) the field's box in the field space, or None where it has none (an MLP over all of space).
    ``appearance``: the per-image appearance embedding, or None; with one, the field is called
    ``field(points, viewdirs, camera_indices)``.
    """

    aabb: torch.Tensor | None
    appearance: torch.nn.Module | None

    def __call__(self, points: torch.Tensor, viewdirs: torch.Tensor) -> dict[str, torch.Tensor]: ...

    def density(self, points: torch.Tensor) -> torch.Tensor: ...
