"""The names nerf-process-data's keys take, torch-free, so that the command checks a key
(``nerf_lightning.cli.keys``) before torch and pycolmap load; the modules that act on them import them from here."""

from __future__ import annotations

# how to install pycolmap, for the messages of whatever needs it
COLMAP_EXTRA = 'pip install -c constraints-cpu.txt -e ".[colmap]"'

# matcher=: which image pairs COLMAP matches (auto: exhaustive for a small capture, sequential for a long one)
MATCHERS = ("auto", "exhaustive", "sequential")
# mapper=: COLMAP's global mapper or its incremental one (auto: both tried, the model that explains more kept)
MAPPERS = ("auto", "global", "incremental")
# camera_model=: COLMAP's camera models this project's transforms.json loader reads, their parameters in COLMAP's
# order (named as transforms.json names them)
CAMERA_PARAMETERS = {
    "SIMPLE_PINHOLE": ("f", "cx", "cy"),
    "PINHOLE": ("fl_x", "fl_y", "cx", "cy"),
    "SIMPLE_RADIAL": ("f", "cx", "cy", "k1"),
    "RADIAL": ("f", "cx", "cy", "k1", "k2"),
    "OPENCV": ("fl_x", "fl_y", "cx", "cy", "k1", "k2", "p1", "p2"),
    "OPENCV_FISHEYE": ("fl_x", "fl_y", "cx", "cy", "k1", "k2", "k3", "k4"),  # Kannala-Brandt: GoPros, wide phone lenses
}
CAMERA_MODELS = tuple(CAMERA_PARAMETERS)
# mask_object=: the colour that marks the object in a mask
MASK_OBJECTS = ("white", "black")
