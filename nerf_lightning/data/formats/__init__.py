"""Loaders of file formats into a :class:`~nerf_lightning.data.scene.Scene`."""

from nerf_lightning.data.formats.blender import load_blender
from nerf_lightning.data.formats.llff import load_llff
from nerf_lightning.data.formats.npz import load_npz, save_npz
from nerf_lightning.data.formats.procedural import load_procedural, make_procedural_scene
from nerf_lightning.data.formats.transforms import load_transforms
from nerf_lightning.data.formats.turntable import load_turntable, make_turntable_capture

__all__ = ["load_blender", "load_llff", "load_npz", "load_procedural", "load_transforms", "load_turntable", "make_procedural_scene",
           "make_turntable_capture", "save_npz"]
