"""The table renderer (``model/renderer=table``, the GPU presets): samples of a fixed count rendered in one pass of
fixed shapes, so that no size in a training step depends on the data and the host never waits for the device."""

from __future__ import annotations

import torch

from nerf_lightning.fields.base import Field
from nerf_lightning.geometry.space import Rays, SceneSpace
from nerf_lightning.rendering.compositing import weights_from_optical_depth
from nerf_lightning.rendering.packed import RaySamples, on_table
from nerf_lightning.rendering.renderer import Renderer, evaluate_field
from nerf_lightning.rendering.rounds import RoundsRenderer


class TableRenderer(Renderer):
    """Samples laid out on a table (:attr:`RaySamples.slots`: the proposal sampler's, or an occupancy grid's with a
    ``capacity`` in training) are all evaluated (:func:`~nerf_lightning.rendering.renderer.evaluate_field`) and
    composited along the rows of the (N + 1, width) table in one pass; the padding's row N has zero optical depth.

    Samples that come without a table (an occupancy grid's outside training: evaluation renders every step) are
    rendered in rounds (:class:`~nerf_lightning.rendering.rounds.RoundsRenderer`, with ``early_stop_eps`` and
    ``samples_per_round``): no training step's shapes depend on them.
    """

    fixed_shapes = True

    def __init__(self, early_stop_eps: float = 1e-4, samples_per_round: int = 16, gradient_scaling_distance: float = 0.0) -> None:
        self.rounds = RoundsRenderer(early_stop_eps, samples_per_round, gradient_scaling_distance)
        self.gradient_scaling_distance = gradient_scaling_distance

    def __call__(self, field: Field, rays: Rays, samples: RaySamples, space: SceneSpace) -> dict[str, torch.Tensor]:
        """N rays from their M packed samples -> ``rgb``, ``depth``, ``accumulation``, ``weights``, ``n_evaluated``
        (:class:`~nerf_lightning.rendering.renderer.Renderer`)."""
        if samples.slots is None:
            return self.rounds(field, rays, samples, space)
        n_rays, width = samples.n_rays, samples.width
        cells = samples.ray_indices * width + samples.slots  # (M,) the padding's in row N
        ray_of = samples.ray_indices.clamp(max=n_rays - 1)  # the padding evaluated on ray N - 1: zero width, no effect
        starts, ends = samples.t_starts, samples.t_ends
        mids = 0.5 * (starts + ends)
        out = evaluate_field(field, rays, ray_of, mids, space, self.gradient_scaling_distance)
        dtype = torch.promote_types(out["rgb"].dtype, torch.float32)
        # the padding's row N has zero optical depth, so zero weights: composited with the rest, dropped from the sums
        weights = weights_from_optical_depth(on_table(out["density"].to(dtype) * (ends - starts).to(dtype), cells, n_rays, width)).weights
        rays_weights = weights[:n_rays]  # (N, width)
        accumulation = rays_weights.sum(dim=1)
        colour = (rays_weights[..., None] * on_table(out["rgb"].to(dtype), cells, n_rays, width)[:n_rays]).sum(dim=1)
        colour = colour + (1.0 - accumulation)[:, None] * space.background.to(dtype)
        depth = (rays_weights * on_table(mids.to(dtype), cells, n_rays, width)[:n_rays]).sum(dim=1) / accumulation.clamp(min=1e-10)
        return {"rgb": colour, "depth": depth, "accumulation": accumulation, "weights": weights.reshape(-1).index_select(0, cells),
                "n_evaluated": (ends > starts).sum()}

    def __repr__(self) -> str:
        return (f"TableRenderer(gradient_scaling_distance={self.gradient_scaling_distance:g}; samples without a table: "
                f"{self.rounds!r})")
