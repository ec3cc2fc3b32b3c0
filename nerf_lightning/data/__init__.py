"""Data: file formats -> Scene -> batches of pixels (image fields), rays (radiance fields) or views (whole images).

Its modules load when first asked for (``nerf_lightning.data.RayDataModule``, as the configs' ``_target_`` names
them), so that the commands' key checks read :mod:`~nerf_lightning.data.choices` without loading torch."""

from __future__ import annotations

from typing import TYPE_CHECKING

from nerf_lightning.lazy import lazy_attributes

_HOMES = {
    "PixelDataModule": "pixels", "RayDataModule": "rays", "Scene": "scene", "SceneDataModule": "scene_data",
    "SparsePoints": "points", "ViewDataModule": "views", "Views": "scene", "default_image": "images",
    "downscale": "images", "load_image": "images", "pixel_grid": "images",
}

__all__ = sorted(_HOMES)

if TYPE_CHECKING:
    from nerf_lightning.data.images import default_image, downscale, load_image, pixel_grid
    from nerf_lightning.data.pixels import PixelDataModule
    from nerf_lightning.data.points import SparsePoints
    from nerf_lightning.data.rays import RayDataModule
    from nerf_lightning.data.scene import Scene, Views
    from nerf_lightning.data.scene_data import SceneDataModule
    from nerf_lightning.data.views import ViewDataModule


__getattr__ = lazy_attributes(__name__, _HOMES)
