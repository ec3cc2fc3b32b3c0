"""Fields: functions of position (and direction) made of encodings and MLPs."""

from nerf_lightning.fields.encodings import SinusoidalEncoding
from nerf_lightning.fields.image_field import ImageField
from nerf_lightning.fields.mlp import MLP
from nerf_lightning.fields.nerf import NeRFField

__all__ = ["MLP", "ImageField", "NeRFField", "SinusoidalEncoding"]
