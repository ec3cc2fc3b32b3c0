"""What every ray sampler is: rays in, packed samples out, state it learns, losses it owns.

A sampler turns N rays into M samples *packed* (nerfacc's layout): ``ray_indices`` (M,), the ray of each sample,
non-decreasing, so that a ray's samples are contiguous and ordered by distance, and ``t_starts``, ``t_ends`` (M,),
the interval of the ray each sample stands for (the field is evaluated at its midpoint). Rays may have different
numbers of samples, none included. One renderer (:class:`~nerf_lightning.rendering.renderer.Renderer`)
renders the samples of every sampler.

Adding a sampler is one file: subclass :class:`RaySampler`, implement :meth:`~RaySampler.sample`, and, if it
learns, :meth:`~RaySampler.update` and :meth:`~RaySampler.losses`; a config in ``conf/model/sampler/`` builds it.
"""

from __future__ import annotations

import torch
from torch import nn

from nerf_lightning.fields.base import Field
from nerf_lightning.geometry.space import Rays, SceneSpace
from nerf_lightning.rendering.packed import RaySamples


class RaySampler(nn.Module):
    """The interface every sampler implements (nerfacc's ``AbstractEstimator``, nerfstudio's ``Sampler``).

    ``grid``: the occupancy grid a sampler marches through (drawn by the viewer), None for the others.
    ``samples_per_step``: the fixed number of samples a training step takes (their count then does not depend on
    the rays: :class:`~nerf_lightning.rendering.packed.FixedShapeSamples`; a ray budget,
    :class:`~nerf_lightning.models.ray_budget.RayBudget`, sizes the rays to fill it), None where it varies.
    ``samples_on_table``: whether its training samples come laid out on a table (``RaySamples.slots``: a fixed
    number a ray, as :meth:`RaySamples.from_edges <nerf_lightning.rendering.packed.RaySamples.from_edges>` gives),
    which ``model/renderer=table`` renders in one pass.
    """

    samples_per_step: int | None = None
    samples_on_table: bool = True

    def __init__(self) -> None:
        super().__init__()
        # an instance attribute, not a class one: a subclass's grid module must not be shadowed by the class's None
        self.grid: nn.Module | None = None

    def sample(self, rays: Rays, space: SceneSpace, field: Field, perturb: bool) -> RaySamples:
        """Samples of ``rays`` (in ``space``'s sampling space) for ``field``; jittered when ``perturb`` (training).
        ``field`` is there for samplers that look at its density (an occupancy grid's alpha threshold)."""
        raise NotImplementedError

    def update(self, step: int, field: Field) -> None:
        """Called before training step ``step``: refresh what the sampler learns from ``field`` (an occupancy grid).
        Nothing by default."""

    def losses(self, samples: RaySamples, rendered: dict[str, torch.Tensor], target_rgb: torch.Tensor) -> dict[str, torch.Tensor]:
        """The sampler's own loss terms (added to the colour loss, logged as ``train/loss_<name>``), given what it
        sampled, what the renderer made of it (``weights`` (M,) among it) and the true colours (N, 3). None by default."""
        return {}


def stratified_edges(t_enter: torch.Tensor, t_exit: torch.Tensor, n_samples: int, perturb: bool) -> torch.Tensor:
    """(N,) ray ranges -> (N, S + 1) edges of S intervals from t_enter to t_exit.

    Evenly spaced; with ``perturb`` each edge moves uniformly at random between the midpoints of the intervals
    beside it (the first and last stay within the range), so that over many steps the field is queried everywhere
    (NeRF's stratified sampling, in nerfstudio's interval form)."""
    steps = torch.linspace(0.0, 1.0, n_samples + 1, device=t_enter.device, dtype=t_enter.dtype)
    edges = t_enter[:, None] + (t_exit - t_enter)[:, None] * steps  # (N, S + 1)
    if perturb:
        mids = 0.5 * (edges[:, 1:] + edges[:, :-1])
        lower = torch.cat([edges[:, :1], mids], dim=-1)
        upper = torch.cat([mids, edges[:, -1:]], dim=-1)
        edges = lower + (upper - lower) * torch.rand_like(edges)
    return edges


def sample_pdf(edges: torch.Tensor, weights: torch.Tensor, n_samples: int, perturb: bool, padding: float = 1e-5) -> torch.Tensor:
    """Inverse-CDF importance sampling (NeRF's hierarchical sampling).

    Args:
        edges: (N, B + 1) sorted bin edges along each ray.
        weights: (N, B) non-negative weights of the bins (need not be normalised; detached here).
        n_samples: points to draw per ray.
        perturb: draw at stratified random quantiles (one in each 1/n_samples slice); otherwise at evenly spaced ones.
        padding: added to every bin's weight before normalising: 1e-5 (NeRF's) only keeps the CDF strictly
            increasing; 0.01 (nerfstudio's ``histogram_padding``, what a proposal sampler uses) also keeps drawing
            some samples from bins the weights call empty, so that what is there can still be found.

    Returns:
        (N, n_samples) sorted distances, distributed within each bin uniformly and across bins in proportion to
        the weights. Not differentiable.
    """
    weights = weights.detach() + padding  # no empty bin: keeps the CDF strictly increasing
    pdf = weights / weights.sum(dim=-1, keepdim=True)
    cdf = torch.cat([torch.zeros_like(pdf[..., :1]), torch.cumsum(pdf, dim=-1)], dim=-1)  # (N, B + 1)
    cdf[..., -1] = 1.0
    if perturb:  # stratified: one uniform draw in each of n_samples equal slices of [0, 1], so no region is skipped
        u = (torch.arange(n_samples, dtype=cdf.dtype, device=cdf.device) + torch.rand(*cdf.shape[:-1], n_samples, dtype=cdf.dtype, device=cdf.device)) / n_samples
    else:
        u = torch.linspace(0.0, 1.0, n_samples, dtype=cdf.dtype, device=cdf.device).expand(*cdf.shape[:-1], n_samples)
    u = u.contiguous()
    above = torch.searchsorted(cdf, u, right=True).clamp(1, cdf.shape[-1] - 1)
    below = above - 1
    cdf_below, cdf_above = torch.gather(cdf, -1, below), torch.gather(cdf, -1, above)
    edges_below, edges_above = torch.gather(edges, -1, below), torch.gather(edges, -1, above)
    fraction = (u - cdf_below) / (cdf_above - cdf_below).clamp(min=1e-10)
    return torch.sort((edges_below + fraction * (edges_above - edges_below)).detach(), dim=-1).values
