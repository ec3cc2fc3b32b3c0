"""Data: file formats -> Scene -> batches of pixels (image fields), rays (radiance fields) or views (whole images)."""

from nerf_lightning.data.images import default_image, downscale, load_image, pixel_grid
from nerf_lightning.data.pixels import PixelDataModule
from nerf_lightning.data.points import SparsePoints
from nerf_lightning.data.rays import RayDataModule
from nerf_lightning.data.scene import Scene, Views
from nerf_lightning.data.scene_data import SceneDataModule
from nerf_lightning.data.views import ViewDataModule

__all__ = ["PixelDataModule", "RayDataModule", "Scene", "SceneDataModule", "SparsePoints", "ViewDataModule", "Views",
           "default_image", "downscale", "load_image", "pixel_grid"]
