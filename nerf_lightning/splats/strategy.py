"""Densification as objects (gsplat's ``strategy/`` is the pattern): a strategy reads each step's statistics after
the backward pass and, every so many steps, grows, prunes or resets the Gaussians through
:meth:`~nerf_lightning.splats.gaussians.Gaussians.edit`, which keeps the optimiser's state in step.

The interface a splat model calls:

- ``after_backward(gaussians, projection, width, height)``: the step's view has been drawn and its loss
  backpropagated; ``projection.means2d.grad`` holds the screen-space gradient of the Gaussians it saw.
- ``after_step(gaussians, step, replace)``: the optimiser has stepped (``step`` steps done): refine if it is time.

Its accumulated statistics are not kept in checkpoints (gsplat's neither): a resumed run starts them afresh at its
next refinement interval.
"""

from __future__ import annotations

import logging
from collections.abc import Callable
from typing import Protocol

import torch
from torch import nn

from nerf_lightning.splats.gaussians import PARAMETERS, Gaussians
from nerf_lightning.splats.projection import Projection, inverse_sigmoid

log = logging.getLogger(__name__)

Replace = Callable[[nn.Module, str, torch.Tensor, torch.Tensor | None], nn.Parameter]


class Strategy(Protocol):
    def after_backward(self, gaussians: Gaussians, projection: Projection, width: int, height: int) -> None: ...

    def after_step(self, gaussians: Gaussians, step: int, replace: Replace) -> None: ...


class DefaultStrategy:
    """3DGS's adaptive density control with gsplat's ``DefaultStrategy`` numbers.

    Every ``refine_every`` steps from ``refine_start`` until ``refine_stop``: a Gaussian whose mean screen-space
    gradient (in units of half the image, averaged over the views that saw it) exceeds ``grow_grad2d`` grows, by a
    clone where its largest scale is at most ``grow_scale3d`` of the scene scale, else by a split into two drawn from
    it with scales / 1.6; then Gaussians under ``prune_opacity`` go, and after ``reset_every`` steps those larger than
    ``prune_scale3d`` of the scene scale too. Every ``reset_every`` steps (until ``refine_stop``) the opacities are
    cut to twice ``prune_opacity`` (their optimiser state zeroed), so that Gaussians the views do not need fade and
    are pruned. ``max_count`` caps the Gaussians: growth that would pass it is dropped, the largest gradients kept.

    Args:
        scene_scale: the scene's size, set by the model from its training cameras (gsplat: 1.1 x their extent).
    """

    def __init__(self, refine_start: int = 500, refine_stop: int = 15_000, refine_every: int = 100, reset_every: int = 3000,
                 grow_grad2d: float = 2e-4, grow_scale3d: float = 0.01, prune_opacity: float = 0.005, prune_scale3d: float = 0.1,
                 max_count: int = 1_000_000, seed: int = 0) -> None:
        self.refine_start, self.refine_stop, self.refine_every, self.reset_every = refine_start, refine_stop, refine_every, reset_every
        self.grow_grad2d, self.grow_scale3d = grow_grad2d, grow_scale3d
        self.prune_opacity, self.prune_scale3d, self.max_count = prune_opacity, prune_scale3d, max_count
        self.scene_scale = 1.0
        self.generator = torch.Generator().manual_seed(seed)
        self.grad_sum: torch.Tensor | None = None  # (N,) the sum of each Gaussian's screen gradient norms
        self.seen: torch.Tensor | None = None  # (N,) how many views saw it

    def after_backward(self, gaussians: Gaussians, projection: Projection, width: int, height: int) -> None:
        grad = projection.means2d.grad
        if grad is None:
            return
        n = len(gaussians)
        if self.grad_sum is None or self.grad_sum.shape[0] != n or self.grad_sum.device != grad.device:
            self.grad_sum, self.seen = grad.new_zeros(n), grad.new_zeros(n)
        norms = (grad * grad.new_tensor([width / 2.0, height / 2.0])).norm(dim=-1)
        self.grad_sum.index_add_(0, projection.ids, norms)
        self.seen.index_add_(0, projection.ids, torch.ones_like(norms))

    def after_step(self, gaussians: Gaussians, step: int, replace: Replace) -> None:
        if self.refine_start <= step < self.refine_stop and step % self.refine_every == 0 and self.grad_sum is not None:
            self.refine(gaussians, step, replace)
        if 0 < step < self.refine_stop and step % self.reset_every == 0:
            self.reset_opacities(gaussians, replace)

    @torch.no_grad()
    def refine(self, gaussians: Gaussians, step: int, replace: Replace) -> None:
        """Grow, then prune (see the class docstring); the statistics start again."""
        n = len(gaussians)
        values = {name: getattr(gaussians, name).detach() for name in PARAMETERS}
        largest = torch.exp(values["log_scales"]).amax(dim=-1)
        mean_grad = self.grad_sum / self.seen.clamp(min=1)
        grow = mean_grad > self.grow_grad2d
        room = max(self.max_count - n, 0)
        if int(grow.sum()) > room:  # over the cap: the largest gradients grow (a split adds one, a clone one)
            keep = mean_grad.masked_fill(~grow, -1).topk(room).indices
            grow = torch.zeros_like(grow).index_fill_(0, keep, True)
        clone = grow & (largest <= self.grow_scale3d * self.scene_scale)
        split = grow & ~clone
        rows = [torch.nonzero(~split).squeeze(1)]  # the Gaussians that stay as they are, clones' originals included
        new = {name: [value[rows[0]]] for name, value in values.items()}
        rows_from = [rows[0]]
        cloned = torch.nonzero(clone).squeeze(1)
        for name, value in values.items():
            new[name].append(value[cloned])
        rows_from.append(torch.full_like(cloned, -1))
        halves = torch.nonzero(split).squeeze(1)
        if len(halves):
            children = split_in_two(values, halves, self.generator)
            for name in PARAMETERS:
                new[name].append(children[name])
            rows_from.append(torch.full((2 * len(halves),), -1, dtype=torch.long, device=halves.device))
        merged = {name: torch.cat(parts) for name, parts in new.items()}
        rows_from = torch.cat(rows_from)
        # prune: too transparent, or (once opacities have been reset) too large
        prune = torch.sigmoid(merged["opacity_logits"]) < self.prune_opacity
        if step > self.reset_every:
            prune |= torch.exp(merged["log_scales"]).amax(dim=-1) > self.prune_scale3d * self.scene_scale
        kept = torch.nonzero(~prune).squeeze(1)
        gaussians.edit({name: value[kept] for name, value in merged.items()}, rows_from[kept], replace)
        log.debug("step %d: %d cloned, %d split, %d pruned: %d Gaussians", step, len(cloned), len(halves), int(prune.sum()), len(kept))
        self.grad_sum = self.seen = None

    @torch.no_grad()
    def reset_opacities(self, gaussians: Gaussians, replace: Replace) -> None:
        logits = gaussians.opacity_logits.detach().clamp(max=inverse_sigmoid(2.0 * self.prune_opacity))
        fresh = torch.full((len(logits),), -1, dtype=torch.long, device=logits.device)  # their optimiser state starts again
        replace(gaussians, "opacity_logits", logits, fresh)


def split_in_two(values: dict[str, torch.Tensor], rows: torch.Tensor, generator: torch.Generator) -> dict[str, torch.Tensor]:
    """Two Gaussians for each of ``rows``: means drawn from the Gaussian (its rotation and scales), scales / 1.6, the
    rest copied; (2 R, ...) each, the first children of every row, then the second."""
    from kornia.geometry.conversions import quaternion_to_rotation_matrix

    quats = torch.nn.functional.normalize(values["quats"][rows], dim=-1)
    scales = torch.exp(values["log_scales"][rows])
    noise = torch.randn(2, len(rows), 3, generator=generator).to(scales.device)
    offsets = (quaternion_to_rotation_matrix(quats)[None] @ (noise * scales[None])[..., None])[..., 0]  # (2, R, 3)
    children = {name: values[name][rows].repeat(2, *([1] * (values[name].dim() - 1))) for name in PARAMETERS}
    children["means"] = (values["means"][rows][None] + offsets).reshape(-1, 3)
    children["log_scales"] = torch.log(scales / 1.6).repeat(2, 1)
    return children
