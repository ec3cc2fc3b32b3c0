"""The rounds renderer (``model/renderer=rounds``, the CPU presets): packed samples of any sampler through a field
to pixels, a few samples of every live ray at a time, spent rays stopped; samples of a fixed shape in one pass."""

from __future__ import annotations

import math
from typing import TYPE_CHECKING

import torch

from nerf_lightning.fields.base import Field
from nerf_lightning.geometry.space import Rays, SceneSpace
from nerf_lightning.rendering.compositing import weights_from_optical_depth
from nerf_lightning.rendering.packed import FixedShapeSamples, RaySamples, composite_on_table
from nerf_lightning.rendering.renderer import Renderer, evaluate_field

if TYPE_CHECKING:
    from nerf_lightning.rendering.samplers.base import RaySampler


class RoundsRenderer(Renderer):
    """Volume rendering of packed samples in rounds.

    The field is evaluated (:func:`~nerf_lightning.rendering.renderer.evaluate_field`) on the next
    ``samples_per_round`` samples of every ray still alive at a time; a ray leaves once its transmittance is below
    ``early_stop_eps``, so the samples behind an opaque surface are never evaluated (on a CPU most of a marched ray's
    cost) and no separate density pass is needed. With ``early_stop_eps=0`` the result equals compositing every
    sample (:func:`~nerf_lightning.rendering.packed.composite_packed`).

    Each round lays its samples out as an (alive rays, samples_per_round) table of dense rows, so that the sums along
    a ray are short float32 cumulative sums that restart at every ray; each row carries in the transmittance its ray
    left the previous round with. Which rays are alive is read back each round: the host waits for the device, which
    on a CPU costs less than the work that stopping spent rays saves (a GPU wants ``model/renderer=table``).

    Samples of a fixed shape (:class:`~nerf_lightning.rendering.packed.FixedShapeSamples`, a training step of
    ``model/sampler=fixed_shape_grid``) are all evaluated and composited in one pass over their table instead
    (:meth:`in_one_pass`): their point is a step whose sizes do not depend on the data.

    ``gradient_scaling_distance``: see :func:`~nerf_lightning.rendering.renderer.evaluate_field`.
    """

    def __init__(self, early_stop_eps: float = 1e-4, samples_per_round: int = 16, gradient_scaling_distance: float = 0.0) -> None:
        if samples_per_round < 1 or early_stop_eps < 0 or gradient_scaling_distance < 0:
            raise ValueError(f"model.renderer needs samples_per_round >= 1, early_stop_eps >= 0 and gradient_scaling_distance >= 0, "
                             f"got {samples_per_round}, {early_stop_eps}, {gradient_scaling_distance}")
        self.early_stop_eps, self.samples_per_round = early_stop_eps, samples_per_round
        self.gradient_scaling_distance = gradient_scaling_distance

    def __call__(self, field: Field, rays: Rays, samples: RaySamples, space: SceneSpace) -> dict[str, torch.Tensor]:
        """N rays from their M packed samples -> ``rgb``, ``depth``, ``accumulation``, ``weights``, ``n_evaluated``
        (:class:`~nerf_lightning.rendering.renderer.Renderer`)."""
        if self.in_one_pass(samples):
            return self.one_pass(field, rays, samples, space)
        n_rays, k = samples.n_rays, self.samples_per_round
        device = rays.origins.device
        # [:n_rays]: a table's padding (ray index N, last) is never a live ray's
        counts = torch.bincount(samples.ray_indices, minlength=n_rays)[:n_rays]
        offsets = torch.cumsum(counts, 0) - counts
        slots = torch.arange(k, device=device)
        transmittance = rays.origins.new_ones(n_rays)
        colour, accumulation, depth_sum = rays.origins.new_zeros(n_rays, 3), rays.origins.new_zeros(n_rays), rays.origins.new_zeros(n_rays)
        evaluated_ids, evaluated_weights = [], []
        n_rounds = math.ceil(int(counts.max()) / k) if len(samples) else 0
        for first in range(0, n_rounds * k, k):
            alive = (counts > first) & (transmittance.detach() >= self.early_stop_eps)
            ray_ids = alive.nonzero()[:, 0]  # (A,)
            if len(ray_ids) == 0:
                break
            slot = first + slots
            valid = slot < counts[ray_ids, None]  # (A, k)
            ids = (offsets[ray_ids, None] + slot)[valid]  # (m,) the round's samples, ray by ray
            ray_of = ray_ids[:, None].expand_as(valid)[valid]
            starts, ends = samples.t_starts[ids], samples.t_ends[ids]
            mids = 0.5 * (starts + ends)
            out = evaluate_field(field, rays, ray_of, mids, space, self.gradient_scaling_distance)
            optical_depth = torch.zeros(valid.shape, dtype=colour.dtype, device=device).masked_scatter(valid, (out["density"] * (ends - starts)).to(colour.dtype))
            rgb = torch.zeros(*valid.shape, 3, dtype=colour.dtype, device=device).masked_scatter(valid[..., None], out["rgb"].to(colour.dtype))
            composited = weights_from_optical_depth(optical_depth, transmittance[ray_ids])
            weights = composited.weights  # (A, k)
            colour = colour.index_add(0, ray_ids, (weights[..., None] * rgb).sum(dim=1))
            accumulation = accumulation.index_add(0, ray_ids, weights.sum(dim=1))
            depth_sum = depth_sum.index_add(0, ray_ids, (weights * torch.zeros_like(weights).masked_scatter(valid, mids)).sum(dim=1))
            transmittance = transmittance.index_copy(0, ray_ids, composited.transmittance_after)
            evaluated_ids.append(ids)
            evaluated_weights.append(weights[valid])
        colour = colour + (1.0 - accumulation)[:, None] * space.background.to(colour)
        weights_all = rays.origins.new_zeros(len(samples))
        if evaluated_ids:
            weights_all = weights_all.index_put((torch.cat(evaluated_ids),), torch.cat(evaluated_weights))
        return {
            "rgb": colour, "depth": depth_sum / accumulation.clamp(min=1e-10), "accumulation": accumulation,
            "weights": weights_all, "n_evaluated": sum(len(ids) for ids in evaluated_ids),
        }

    def in_one_pass(self, samples: RaySamples) -> bool:
        """Whether ``samples`` are composited in one pass over their table, not in rounds: those of a fixed shape."""
        return isinstance(samples, FixedShapeSamples)

    def steps_in_one_pass(self, sampler: RaySampler) -> bool:
        """Whether every training step of ``sampler`` is composited in one pass (its sizes then do not depend on the
        data): a sampler of a fixed number of samples a step."""
        return sampler.samples_per_step is not None

    def one_pass(self, field: Field, rays: Rays, samples: RaySamples, space: SceneSpace) -> dict[str, torch.Tensor]:
        """Every sample of a table (``samples.slots``) evaluated and composited in one pass
        (:func:`~nerf_lightning.rendering.packed.composite_on_table`); the padding (ray N, zero width) is evaluated
        on ray N - 1, to no effect."""
        mids = 0.5 * (samples.t_starts + samples.t_ends)
        ray_of = samples.ray_indices.clamp(max=samples.n_rays - 1)
        out = evaluate_field(field, rays, ray_of, mids, space, self.gradient_scaling_distance)
        rendered = composite_on_table(out["rgb"], out["density"], samples, space.background)
        rendered["n_evaluated"] = (samples.t_ends > samples.t_starts).sum()
        return rendered

    def __repr__(self) -> str:
        return (f"RoundsRenderer(early_stop_eps={self.early_stop_eps:g}, samples_per_round={self.samples_per_round}, "
                f"gradient_scaling_distance={self.gradient_scaling_distance:g})")
