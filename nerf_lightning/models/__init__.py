"""LightningModules: a field, its loss and metrics, and its optimiser."""

from nerf_lightning.models.image_field import ImageFieldModule

__all__ = ["ImageFieldModule"]
