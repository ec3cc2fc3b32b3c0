"""LightningModules: a field, its loss and metrics, and its optimiser."""

from nerf_lightning.models.image_field import ImageFieldModule
from nerf_lightning.models.radiance_field import RadianceFieldModule
from nerf_lightning.models.splat import SplatModule

__all__ = ["ImageFieldModule", "RadianceFieldModule", "SplatModule"]
