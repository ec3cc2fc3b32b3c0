"""Data: file formats -> images and scenes -> batches of pixels or rays."""

from nerf_lightning.data.images import default_image, downscale, load_image, pixel_grid
from nerf_lightning.data.pixels import PixelDataModule

__all__ = ["PixelDataModule", "default_image", "downscale", "load_image", "pixel_grid"]
