"""The names the data side's keys take, torch-free, so that the commands check a key (``nerf_lightning.cli.keys``)
before torch loads; the modules that act on them import them from here."""

from __future__ import annotations

# render.path of nerf-render and data.render_path: the scene's held-out or render cameras, or a path made around it
RENDER_PATHS = ("test", "orbit", "spiral")
# ... or a camera path file (nerf-render's render.path): nerfstudio's camera_path.json or a rendered path's transforms.json
CAMERA_PATH_SUFFIX = ".json"


def is_camera_path_file(path: object) -> bool:
    """``render.path`` names a camera path file rather than one of :data:`RENDER_PATHS`."""
    return str(path).lower().endswith(CAMERA_PATH_SUFFIX)
# data.object_box: where an object's box comes from (nerf_lightning.data.object_box), or null for none
OBJECT_BOXES = ("visual_hull",)
# the procedural scene's smallest number of views: its val and test splits take every tenth
PROCEDURAL_MIN_VIEWS = 10
