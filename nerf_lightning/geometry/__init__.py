"""Cameras and rays. Everything after loading speaks the OpenCV convention: x right, y down, z forward."""

from nerf_lightning.geometry.cameras import (
    camera_to_world,
    look_at,
    opengl_to_opencv,
    pinhole_camera,
    pixel_to_camera,
    pixel_to_ray,
    validate_c2w,
)
from nerf_lightning.geometry.rays import image_pixels, image_rays, sample_along_rays

__all__ = [
    "camera_to_world",
    "image_pixels",
    "image_rays",
    "look_at",
    "opengl_to_opencv",
    "pinhole_camera",
    "pixel_to_camera",
    "pixel_to_ray",
    "sample_along_rays",
    "validate_c2w",
]
