"""NeRF's hierarchical sampling: a coarse network on stratified samples decides where the field is sampled."""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import nn

from nerf_lightning.fields.base import Field
from nerf_lightning.geometry.space import Rays, SceneSpace
from nerf_lightning.rendering.samplers.base import RaySampler, RaySamples, sample_pdf, stratified_edges
from nerf_lightning.rendering.volume import composite


class HierarchicalSampler(RaySampler):
    """Coarse-to-fine sampling (Mildenhall et al. 2020), the coarse network owned by the sampler.

    The coarse field renders ``n_samples`` stratified intervals of each ray; ``n_fine_samples`` more edges are drawn
    from its weights by inverse-CDF sampling (:func:`sample_pdf`), and the field is sampled on the union of both
    sets of edges: ``n_samples + n_fine_samples`` intervals a ray. The coarse network learns from its own colour
    loss (``coarse_rgb``, the MSE of its rendering).

    Args:
        coarse_field: the coarse network (a :class:`~nerf_lightning.fields.base.Field`), trained with the model.
        n_samples: stratified intervals per ray for the coarse network.
        n_fine_samples: importance-sampled edges per ray.
    """

    def __init__(self, coarse_field: nn.Module, n_samples: int = 64, n_fine_samples: int = 128) -> None:
        super().__init__()
        if n_samples < 1 or n_fine_samples < 0:
            raise ValueError(f"HierarchicalSampler needs n_samples >= 1 and n_fine_samples >= 0, got {n_samples}, {n_fine_samples}")
        self.coarse_field = coarse_field
        self.n_samples, self.n_fine_samples = n_samples, n_fine_samples

    def sample(self, rays: Rays, space: SceneSpace, field: Field, perturb: bool) -> RaySamples:
        t_enter, t_exit = space.ray_range(rays)
        edges = stratified_edges(t_enter, t_exit, self.n_samples, perturb)  # (N, S + 1)
        mids = 0.5 * (edges[:, 1:] + edges[:, :-1])  # (N, S)
        points = rays.origins[:, None, :] + rays.directions[:, None, :] * mids[..., None]
        out = self.coarse_field(space.to_field(points), rays.viewdirs[:, None, :].expand_as(points))
        coarse = composite(out["rgb"], out["density"], mids, edges[:, 1:] - edges[:, :-1], space.background)
        fine = sample_pdf(edges, coarse["weights"], self.n_fine_samples, perturb)
        all_edges = torch.sort(torch.cat([edges.detach(), fine], dim=-1), dim=-1).values
        return RaySamples.from_edges(all_edges, coarse_rgb=coarse["rgb"])

    def losses(self, samples: RaySamples, rendered: dict[str, torch.Tensor], target_rgb: torch.Tensor) -> dict[str, torch.Tensor]:
        return {"coarse_rgb": F.mse_loss(samples.extras["coarse_rgb"], target_rgb)}

    def extra_repr(self) -> str:
        return f"n_samples={self.n_samples}, n_fine_samples={self.n_fine_samples}"
