"""Rendering: samplers (rays -> packed samples), the occupancy grid, compositing weights, and volume rendering of the samples."""

from nerf_lightning.rendering.compositing import (
    Compositing,
    weights_from_alpha,
    weights_from_alpha_packed,
    weights_from_optical_depth,
    weights_from_optical_depth_packed,
)
from nerf_lightning.rendering.occupancy import OccupancyGrid, march_rays
from nerf_lightning.rendering.packed import FixedShapeSamples, composite_on_table, composite_packed, exclusive_sum_packed
from nerf_lightning.rendering.renderer import Renderer, evaluate_field
from nerf_lightning.rendering.rounds import RoundsRenderer
from nerf_lightning.rendering.table import TableRenderer
from nerf_lightning.rendering.samplers import (
    FixedShapeGridSampler,
    HierarchicalSampler,
    OccupancyGridSampler,
    ProposalSampler,
    RaySampler,
    RaySamples,
    StratifiedSampler,
    sample_pdf,
)
from nerf_lightning.rendering.volume import composite, render_weights, transmittance

__all__ = [
    "Compositing", "FixedShapeGridSampler", "FixedShapeSamples", "HierarchicalSampler", "OccupancyGrid", "OccupancyGridSampler", "ProposalSampler", "RaySampler", "RaySamples", "Renderer", "RoundsRenderer",
    "StratifiedSampler", "TableRenderer", "evaluate_field",
    "composite", "composite_on_table", "composite_packed", "exclusive_sum_packed", "march_rays", "render_weights", "sample_pdf", "transmittance",
    "weights_from_alpha", "weights_from_alpha_packed", "weights_from_optical_depth", "weights_from_optical_depth_packed",
]

