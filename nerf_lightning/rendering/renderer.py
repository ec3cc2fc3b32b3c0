"""Volume rendering of packed samples: what every renderer shares, and the choice between them.

A renderer takes N rays and M packed samples of them (:class:`~nerf_lightning.rendering.packed.RaySamples`, any
sampler's) through a field to pixels, and learns from the samples how: samples of a fixed shape
(:class:`~nerf_lightning.rendering.packed.FixedShapeSamples`) are composited in one pass over their table by
every renderer. There are two, one file each, chosen by the config group ``model/renderer``:

- ``rounds`` (:class:`~nerf_lightning.rendering.rounds.RoundsRenderer`, the CPU presets): the field evaluated on the
  next few samples of every ray still alive, so that spent rays stop.
- ``table`` (:class:`~nerf_lightning.rendering.table.TableRenderer`, the GPU presets of the proposal sampler): every
  sample laid out on a table (a fixed number a ray) rendered in one pass, so that the host never waits for the device.

Both evaluate the field through :func:`evaluate_field`, the one place a field meets samples, and composite with
:mod:`~nerf_lightning.rendering.compositing`'s weights.
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Any

import torch

from nerf_lightning.fields.base import Field
from nerf_lightning.geometry.space import Rays, SceneSpace
from nerf_lightning.rendering.packed import RaySamples

if TYPE_CHECKING:
    from nerf_lightning.rendering.samplers.base import RaySampler


class Renderer:
    """What a model asks of its renderer: ``renderer(field, rays, samples, space)`` -> ``rgb`` (N, 3) with the
    background blended in by 1 - accumulation, ``depth`` (N,) (the expected t at which a ray ends, given that it
    ends), ``accumulation`` (N,), ``weights`` (M,) each sample's weight (0 for samples never evaluated) and
    ``n_evaluated`` (how many samples the field saw)."""

    def __call__(self, field: Field, rays: Rays, samples: RaySamples, space: SceneSpace) -> dict[str, Any]:
        raise NotImplementedError

    def steps_in_one_pass(self, sampler: RaySampler) -> bool:
        """Whether every training step of ``sampler``'s samples is rendered in one pass, its sizes then independent of
        the data (what a compiled step needs)."""
        return False


def check_compilable(renderer: Renderer, sampler: RaySampler) -> None:
    """ValueError naming the keys unless a training step of ``sampler`` through ``renderer`` has sizes that do not
    depend on the data (``model.compile=true``): any other step would compile anew each time."""
    if not renderer.steps_in_one_pass(sampler):
        raise ValueError("model.compile=true needs a training step of fixed shapes: model/sampler=fixed_shape_grid, or "
                         "model/renderer=table with a sampler of a fixed number of samples a ray (proposal, stratified), "
                         "as the GPU presets have; any other step's sizes depend on the data, so each would compile anew")


def evaluate_field(field: Field, rays: Rays, ray_of: torch.Tensor, mids: torch.Tensor, space: SceneSpace,
                   gradient_scaling_distance: float = 0.0) -> dict[str, torch.Tensor]:
    """The field at M samples: ``ray_of`` (M,) which ray each is on, ``mids`` (M,) its t -> ``density`` (M,) and
    ``rgb`` (M, 3). The point is taken to the field's space (``space.to_field``); a field with per-image appearance
    is told each sample's image.

    ``gradient_scaling_distance`` d > 0 (Floaters No More, Philip & Deschaintre 2023; nerfstudio's
    ``use_gradient_scaling``): in training, the gradients reaching the field from a sample at distance t < d are
    scaled by (t / d)^2 (the values are unchanged). A camera's first stretch of space is seen by it alone and gets as
    many gradients as the subject: without the scaling, a proposal sampler, which samples there densely, lets each
    camera paint its picture on a fog just in front of it (the "floaters" of real captures). d is in the sampling
    space's units: about the distance from the cameras to the subject (1 in a normalised capture)."""
    points, viewdirs = space.to_field(rays.points(ray_of, mids)), rays.viewdirs[ray_of]
    if getattr(field, "appearance", None) is not None:  # which image each sample's ray came from
        out = field(points, viewdirs, None if rays.camera_indices is None else rays.camera_indices[ray_of])
    else:
        out = field(points, viewdirs)
    if gradient_scaling_distance > 0 and torch.is_grad_enabled():
        scale = (mids / gradient_scaling_distance).square().clamp(max=1.0)  # (M,)
        out = {"density": scale_gradient(out["density"], scale), "rgb": scale_gradient(out["rgb"], scale[:, None])}
    return out


def scale_gradient(values: torch.Tensor, scale: torch.Tensor) -> torch.Tensor:
    """``values`` unchanged, with the gradient flowing back through them multiplied by ``scale`` (broadcast)."""
    return values * scale + (values * (1.0 - scale)).detach()
