"""LightningModules: a field, its loss and metrics, and its optimiser.

The modules load when first asked for (``nerf_lightning.models.SplatModule``, as the configs' ``_target_`` names
them), so that importing :mod:`~nerf_lightning.models.contract`, which the commands, the outputs and the viewer read
a model through, loads none of the models.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

from nerf_lightning.lazy import lazy_attributes

_HOMES = {"ImageFieldModule": "image_field", "RadianceFieldModule": "radiance_field", "SplatModule": "splat"}

__all__ = sorted(_HOMES)

if TYPE_CHECKING:
    from nerf_lightning.models.image_field import ImageFieldModule
    from nerf_lightning.models.radiance_field import RadianceFieldModule
    from nerf_lightning.models.splat import SplatModule


__getattr__ = lazy_attributes(__name__, _HOMES)
