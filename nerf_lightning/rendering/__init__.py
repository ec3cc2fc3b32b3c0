"""Rendering: samples along rays and discrete volume rendering, as plain functions over tensors."""

from nerf_lightning.rendering.renderer import render_rays
from nerf_lightning.rendering.samplers import sample_intervals, sample_pdf
from nerf_lightning.rendering.volume import composite, render_weights, transmittance

__all__ = ["composite", "render_rays", "render_weights", "sample_intervals", "sample_pdf", "transmittance"]
