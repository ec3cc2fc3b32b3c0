"""Fields: functions of position (and direction) made of encodings and MLPs."""

from nerf_lightning.fields.appearance import AppearanceEmbedding
from nerf_lightning.fields.base import Field
from nerf_lightning.fields.encodings import SinusoidalEncoding, SphericalHarmonicsEncoding
from nerf_lightning.fields.grid import DensityField, GridField
from nerf_lightning.fields.hash_grid import HashGridEncoding
from nerf_lightning.fields.image_field import ImageField
from nerf_lightning.fields.mlp import MLP
from nerf_lightning.fields.nerf import NeRFField
from nerf_lightning.fields.tensorf import TensorVMEncoding

__all__ = [
    "MLP", "AppearanceEmbedding", "DensityField", "Field", "GridField", "HashGridEncoding", "ImageField", "NeRFField", "SinusoidalEncoding", "SphericalHarmonicsEncoding",
    "TensorVMEncoding",
]
