"""Ray samplers: rays in, packed samples out (see :mod:`~nerf_lightning.rendering.samplers.base`)."""

from nerf_lightning.rendering.samplers.base import RaySampler, RaySamples, sample_pdf, stratified_edges
from nerf_lightning.rendering.samplers.fixed_shape_grid import FixedShapeGridSampler
from nerf_lightning.rendering.samplers.hierarchical import HierarchicalSampler
from nerf_lightning.rendering.samplers.occupancy_grid import OccupancyGridSampler
from nerf_lightning.rendering.samplers.proposal import ProposalSampler
from nerf_lightning.rendering.samplers.stratified import StratifiedSampler

__all__ = ["FixedShapeGridSampler", "HierarchicalSampler", "OccupancyGridSampler", "ProposalSampler", "RaySampler", "RaySamples", "StratifiedSampler", "sample_pdf", "stratified_edges"]
