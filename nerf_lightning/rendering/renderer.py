"""The one renderer: packed samples of any sampler through a field to pixels, in rounds, stopping spent rays."""

from __future__ import annotations

import math

import torch

from nerf_lightning.fields.base import Field
from nerf_lightning.geometry.space import Rays, SceneSpace
from nerf_lightning.rendering.compositing import weights_from_optical_depth
from nerf_lightning.rendering.packed import RaySamples, on_table


class VolumeRenderer:
    """Volume rendering of packed samples (:mod:`nerf_lightning.rendering.compositing`'s weights), in rounds.

    The field is evaluated on the next ``samples_per_round`` samples of every ray still alive at a time; a ray
    leaves once its transmittance is below ``early_stop_eps``, so the samples behind an opaque surface are never
    evaluated (on a CPU most of a marched ray's cost) and no separate density pass is needed. With
    ``early_stop_eps=0`` the result equals compositing every sample (:func:`~nerf_lightning.rendering.packed.composite_packed`).

    Each round lays its samples out as an (alive rays, samples_per_round) table of dense rows, so that the sums along
    a ray are short float32 cumulative sums that restart at every ray; each row carries in the transmittance its ray
    left the previous round with.

    ``gradient_scaling_distance`` d > 0 (Floaters No More, Philip & Deschaintre 2023; nerfstudio's
    ``use_gradient_scaling``): in training, the gradients reaching the field from a sample at distance t < d are
    scaled by (t / d)^2 (the values are unchanged). A camera's first stretch of space is seen by it alone and gets as
    many gradients as the subject: without the scaling, a proposal sampler, which samples there densely, lets
    each camera paint its picture on a fog just in front of it (the "floaters" of real captures). d is in the
    sampling space's units: about the distance from the cameras to the subject (1 in a normalised capture).

    ``fixed_shapes`` (GPU presets): samples of a fixed count laid out on a table (:attr:`RaySamples.slots`, from
    the proposal sampler or an occupancy grid with a ``capacity``) are rendered in one pass, every sample evaluated
    and composited along the table's rows, so that no size depends on the data and the host never waits for the
    device (the rounds read each round's live rays back). On a CPU the rounds are the faster: stopping spent rays
    saves more work than the waits cost.
    """

    def __init__(self, early_stop_eps: float = 1e-4, samples_per_round: int = 16, gradient_scaling_distance: float = 0.0,
                 fixed_shapes: bool = False) -> None:
        if samples_per_round < 1 or early_stop_eps < 0 or gradient_scaling_distance < 0:
            raise ValueError(f"VolumeRenderer needs samples_per_round >= 1, early_stop_eps >= 0 and gradient_scaling_distance >= 0, "
                             f"got {samples_per_round}, {early_stop_eps}, {gradient_scaling_distance}")
        self.early_stop_eps, self.samples_per_round = early_stop_eps, samples_per_round
        self.gradient_scaling_distance = gradient_scaling_distance
        self.fixed_shapes = fixed_shapes

    def __call__(self, field: Field, rays: Rays, samples: RaySamples, space: SceneSpace) -> dict[str, torch.Tensor]:
        """Render N rays from their packed samples.

        Args:
            field: evaluated at each interval's midpoint, passed through ``space.to_field``, with the ray's view direction.
            rays: the N rays in the sampling space.
            samples: M packed samples of them.
            space: the scene space (the field-space map and the background).

        Returns:
            ``rgb`` (N, 3) with the background blended in by 1 - accumulation; ``depth`` (N,) the expected t at
            which a ray ends, given that it ends; ``accumulation`` (N,); ``weights`` (M,) each sample's weight
            (0 for samples never evaluated); ``n_evaluated``, how many samples the field saw (an int).
        """
        if self.fixed_shapes and samples.slots is not None:
            return self._render_table(field, rays, samples, space)
        n_rays, k = samples.n_rays, self.samples_per_round
        device = rays.origins.device
        # [:n_rays]: a fixed capacity's padding (ray index N, last) is never a live ray's
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
            points, viewdirs = space.to_field(rays.points(ray_of, mids)), rays.viewdirs[ray_of]
            if getattr(field, "appearance", None) is not None:  # a field with per-image appearance: which image
                out = field(points, viewdirs, None if rays.camera_indices is None else rays.camera_indices[ray_of])
            else:
                out = field(points, viewdirs)
            if self.gradient_scaling_distance > 0 and torch.is_grad_enabled():
                scale = (mids / self.gradient_scaling_distance).square().clamp(max=1.0)  # (m,)
                out = {"density": scale_gradient(out["density"], scale), "rgb": scale_gradient(out["rgb"], scale[:, None])}
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

    def _render_table(self, field: Field, rays: Rays, samples: RaySamples, space: SceneSpace) -> dict[str, torch.Tensor]:
        """Every sample in one pass, composited along the rows of the (N + 1, width) table (see the class)."""
        n_rays, width = samples.n_rays, samples.width
        cells = samples.ray_indices * width + samples.slots  # (M,) the padding's in row N
        ray_of = samples.ray_indices.clamp(max=n_rays - 1)  # the padding evaluated on ray N - 1: zero width, no effect
        starts, ends = samples.t_starts, samples.t_ends
        mids = 0.5 * (starts + ends)
        points, viewdirs = space.to_field(rays.points(ray_of, mids)), rays.viewdirs[ray_of]
        if getattr(field, "appearance", None) is not None:
            out = field(points, viewdirs, None if rays.camera_indices is None else rays.camera_indices[ray_of])
        else:
            out = field(points, viewdirs)
        if self.gradient_scaling_distance > 0 and torch.is_grad_enabled():
            scale = (mids / self.gradient_scaling_distance).square().clamp(max=1.0)
            out = {"density": scale_gradient(out["density"], scale), "rgb": scale_gradient(out["rgb"], scale[:, None])}
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
        return (f"VolumeRenderer(early_stop_eps={self.early_stop_eps:g}, samples_per_round={self.samples_per_round}, "
                f"gradient_scaling_distance={self.gradient_scaling_distance:g}, fixed_shapes={self.fixed_shapes})")


def scale_gradient(values: torch.Tensor, scale: torch.Tensor) -> torch.Tensor:
    """``values`` unchanged, with the gradient flowing back through them multiplied by ``scale`` (broadcast)."""
    return values * scale + (values * (1.0 - scale)).detach()
