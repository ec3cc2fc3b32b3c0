"""A user's own photos or video to a posed capture: frames picked from a video, photos turned upright, COLMAP run
in-process through pycolmap, the result written as nerfstudio's transforms.json (``nerf-process-data``)."""

from nerf_lightning.capture.compare import compare_with_reference
from nerf_lightning.capture.process import format_report, process_capture

__all__ = ["compare_with_reference", "format_report", "process_capture"]
