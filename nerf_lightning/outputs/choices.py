"""The names nerf-export's keys take, torch-free, so that the command checks a key (``nerf_lightning.cli.keys``)
before torch loads; the modules that act on them import them from here."""

from __future__ import annotations

# format=: what nerf-export writes (a mesh in any of them; a model of Gaussians as a splat PLY)
EXPORT_FORMATS = ("ply", "obj", "glb")
# frame=: the coordinates a mesh is written in: the capture's own (its transforms.json or poses) or the scene's
MESH_FRAMES = ("capture", "scene")
