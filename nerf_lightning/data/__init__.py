"""Data: file formats -> Scene -> batches of pixels (image fields) or rays (radiance fields)."""

from nerf_lightning.data.images import default_image, downscale, load_image, pixel_grid
from nerf_lightning.data.pixels import PixelDataModule
from nerf_lightning.data.rays import RayDataModule
from nerf_lightning.data.scene import Scene, Views

__all__ = ["PixelDataModule", "RayDataModule", "Scene", "Views", "default_image", "downscale", "load_image", "pixel_grid"]
