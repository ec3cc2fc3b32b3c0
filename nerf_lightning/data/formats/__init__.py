"""Loaders of file formats into a :class:`~nerf_lightning.data.scene.Scene`."""

from nerf_lightning.data.formats.blender import load_blender
from nerf_lightning.data.formats.npz import load_npz, save_npz
from nerf_lightning.data.formats.procedural import load_procedural, make_procedural_scene

__all__ = ["load_blender", "load_npz", "load_procedural", "make_procedural_scene", "save_npz"]
