"""The plain sampler: S stratified intervals between near and far on every ray (NeRF, the course)."""

from __future__ import annotations

from nerf_lightning.fields.base import Field
from nerf_lightning.geometry.space import Rays, SceneSpace
from nerf_lightning.rendering.samplers.base import RaySampler, RaySamples, stratified_edges


class StratifiedSampler(RaySampler):
    """``n_samples`` intervals a ray from near to far, evenly spaced, jittered in training (:func:`stratified_edges`)."""

    def __init__(self, n_samples: int = 64) -> None:
        super().__init__()
        if n_samples < 1:
            raise ValueError(f"StratifiedSampler needs n_samples >= 1, got {n_samples}")
        self.n_samples = n_samples

    def sample(self, rays: Rays, space: SceneSpace, field: Field, perturb: bool) -> RaySamples:
        t_enter, t_exit = space.ray_range(rays)
        return RaySamples.from_edges(stratified_edges(t_enter, t_exit, self.n_samples, perturb))

    def extra_repr(self) -> str:
        return f"n_samples={self.n_samples}"
