"""The names nerf-export's and nerf-eval's keys take, torch-free, so that the commands check a key
(``nerf_lightning.cli.keys``) before torch loads; the modules that act on them import them from here."""

from __future__ import annotations

# the formats a mesh is written in
MESH_FORMATS = ("ply", "obj", "glb")
# format=: what nerf-export writes (a mesh in any of the mesh formats; a model of Gaussians as a splat PLY or SPZ)
EXPORT_FORMATS = (*MESH_FORMATS, "spz")
# frame=: the coordinates a mesh is written in: the capture's own (its transforms.json or poses) or the scene's
MESH_FRAMES = ("capture", "scene")
# eval.lpips=: where LPIPS's weights come from (nerf_lightning.outputs.lpips.load_lpips)
LPIPS_MODES = ("auto", "download", "off")
# the environment variable naming LPIPS's weights (a file, or a folder of them) once for every nerf-eval and
# nerf-bench, where eval.lpips_weights does not name them
LPIPS_WEIGHTS_VARIABLE = "NERF_LIGHTNING_LPIPS"
