"""Rendering: samples along rays (stratified, hierarchical, or marched through an occupancy grid) and volume rendering."""

from nerf_lightning.rendering.occupancy import OccupancyGrid, PackedSamples, march_rays, ray_aabb_intersect
from nerf_lightning.rendering.packed import composite_packed, exclusive_sum_packed
from nerf_lightning.rendering.renderer import render_rays, render_rays_marched
from nerf_lightning.rendering.samplers import sample_intervals, sample_pdf
from nerf_lightning.rendering.volume import composite, render_weights, transmittance

__all__ = [
    "OccupancyGrid", "PackedSamples", "composite", "composite_packed", "exclusive_sum_packed", "march_rays", "ray_aabb_intersect",
    "render_rays", "render_rays_marched", "render_weights", "sample_intervals", "sample_pdf", "transmittance",
]
