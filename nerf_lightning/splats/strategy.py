"""Densification as objects (gsplat's ``strategy/`` is the pattern): a strategy reads each step's statistics after
the backward pass and, every so many steps, grows, prunes or resets the Gaussians through
:meth:`~nerf_lightning.splats.gaussians.Gaussians.edit`, which keeps the optimiser's state in step.

The interface a splat model calls:

- ``absgrad``: whether ``after_backward`` reads the absolute screen-space gradients; the model then asks the
  rasteriser to keep them.
- ``after_backward(gaussians, projection, width, height)``: the step's view has been drawn and its loss
  backpropagated; ``projection.means2d.grad`` holds the screen-space gradient of the Gaussians it saw, and, where
  ``absgrad`` asked for it, ``projection.means2d.absgrad`` (M, 2) the sum over the pixels of the absolute values of
  each pixel's share of it (:func:`~nerf_lightning.splats.rasterize_core.keep_absgrad`).
- ``after_step(gaussians, step, replace, means_lr)``: the optimiser has stepped (``step`` steps done) with the
  means at learning rate ``means_lr`` (MCMC scales its noise by it): refine if it is time.
- ``loss(gaussians)``: a regulariser the model adds to its loss (MCMC's), or None.

Three strategies: :class:`DefaultStrategy` (3DGS's adaptive density control), :class:`ViewConsistentStrategy` (the
same where the views agree: FastGS's) and :class:`~nerf_lightning.splats.mcmc.MCMCStrategy` (3DGS as Markov chain
Monte Carlo, in its own file). Their accumulated statistics and random state are not kept in checkpoints (gsplat's
neither): a resumed run starts them afresh at its next refinement interval.
"""

from __future__ import annotations

import logging
from collections.abc import Callable
from typing import Protocol

import torch
from torch import nn

from nerf_lightning.splats.gaussians import PARAMETERS, Gaussians
from nerf_lightning.splats.projection import Projection, inverse_sigmoid, views_seeing

log = logging.getLogger(__name__)

Replace = Callable[[nn.Module, str, torch.Tensor, torch.Tensor | None], nn.Parameter]


class Strategy(Protocol):
    absgrad: bool

    def after_backward(self, gaussians: Gaussians, projection: Projection, width: int, height: int) -> None: ...

    def after_step(self, gaussians: Gaussians, step: int, replace: Replace, means_lr: float) -> None: ...

    def loss(self, gaussians: Gaussians) -> torch.Tensor | None: ...


class DefaultStrategy:
    """3DGS's adaptive density control with gsplat's ``DefaultStrategy`` numbers.

    Every ``refine_every`` steps from ``refine_start`` until ``refine_stop``: a Gaussian whose mean screen-space
    gradient (in units of half the image, averaged over the views that saw it) exceeds ``grow_grad2d`` grows, by a
    clone where its largest scale is at most ``grow_scale3d`` of the scene scale, else by a split into two drawn from
    it with scales / 1.6; then Gaussians under ``prune_opacity`` go, and after ``prune_large_after`` steps (unset: the
    first reset) those larger than ``prune_scale3d`` of the scene scale too. Every ``reset_every`` steps (until ``refine_stop``) the opacities are
    cut to twice ``prune_opacity`` (their optimiser state zeroed), so that Gaussians the views do not need fade and
    are pruned. ``max_count`` caps the Gaussians: growth that would pass it is dropped, the largest gradients kept.

    With ``absgrad`` (AbsGS, Ye et al. 2024; gsplat's ``absgrad``), the gradient a Gaussian grows by is the sum over
    its pixels of the absolute value of each pixel's pull on its centre, not the norm of their sum. Over fine detail
    (a row of dots, a weave) the pixels pull a large Gaussian in opposite directions, the pulls cancel and the
    Gaussian is never split, so the detail stays blurred; their absolute values do not cancel. The sums are larger,
    so the threshold is too: gsplat pairs absgrad with four times its ``grow_grad2d``.

    With ``prune_near_cameras`` (a fraction of the scene scale), each refinement also prunes the Gaussians within
    that distance of a training camera's centre whose centre fewer than ``near_cameras_min_views`` training views
    see. Such a Gaussian fills the near field of a camera or two: the views that see it can explain it as anything,
    so nothing holds it to the scene, and a view between them (a held-out one) finds a blob or a needle across it.
    Photos walked round a subject have the cameras close to one another and leave many of these. The cameras are
    the loaded ones, also where camera refinement corrects them in training.

    Args:
        scene_scale: the scene's size, set by the model from its training cameras (gsplat: 1.1 x their extent).
        cameras: the training views' (K (V, 3, 3), c2w (V, 4, 4), height, width), set by the model likewise; needed
            only by ``prune_near_cameras``.
    """

    def __init__(self, refine_start: int = 500, refine_stop: int = 15_000, refine_every: int = 100, reset_every: int = 3000,
                 grow_grad2d: float = 2e-4, grow_scale3d: float = 0.01, prune_opacity: float = 0.005, prune_scale3d: float = 0.1,
                 max_count: int = 1_000_000, prune_large_after: int | None = None, prune_near_cameras: float | None = None,
                 near_cameras_min_views: int = 5, seed: int = 0, absgrad: bool = False) -> None:
        self.refine_start, self.refine_stop, self.refine_every, self.reset_every = refine_start, refine_stop, refine_every, reset_every
        self.grow_grad2d, self.grow_scale3d = grow_grad2d, grow_scale3d
        self.prune_opacity, self.prune_scale3d, self.max_count = prune_opacity, prune_scale3d, max_count
        self.prune_large_after = reset_every if prune_large_after is None else prune_large_after
        self.prune_near_cameras, self.near_cameras_min_views = prune_near_cameras, near_cameras_min_views
        self.absgrad = absgrad
        self.scene_scale = 1.0
        self.cameras: tuple[torch.Tensor, torch.Tensor, int, int] | None = None
        self.generator = torch.Generator().manual_seed(seed)
        self.grad_sum: torch.Tensor | None = None  # (N,) the sum of each Gaussian's screen gradient norms
        self.seen: torch.Tensor | None = None  # (N,) how many views saw it

    def after_backward(self, gaussians: Gaussians, projection: Projection, width: int, height: int) -> None:
        grad = projection.means2d.grad
        if grad is None:
            return
        if self.absgrad:
            grad = getattr(projection.means2d, "absgrad", None)
            if grad is None:
                raise RuntimeError("model.strategy.absgrad needs the rasteriser's absolute screen-space gradients, and "
                                   "this view was drawn without them (drawer.rasterize(..., absgrad=True) keeps them)")
        n = len(gaussians)
        if self.grad_sum is None or self.grad_sum.shape[0] != n or self.grad_sum.device != grad.device:
            self.grad_sum, self.seen = grad.new_zeros(n), grad.new_zeros(n)
        norms = (grad * grad.new_tensor([width / 2.0, height / 2.0])).norm(dim=-1)
        self.grad_sum.index_add_(0, projection.ids, norms)
        self.seen.index_add_(0, projection.ids, torch.ones_like(norms))

    def after_step(self, gaussians: Gaussians, step: int, replace: Replace, means_lr: float = 0.0) -> None:
        """(``means_lr`` is not used here.)"""
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
        grow = self.growing(mean_grad)
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
        # prune: too transparent, or (once opacities have been reset, or after prune_large_after) too large
        prune = torch.sigmoid(merged["opacity_logits"]) < self.prune_opacity
        if step > self.prune_large_after:
            prune |= torch.exp(merged["log_scales"]).amax(dim=-1) > self.prune_scale3d * self.scene_scale
        near = self.near_few_cameras(merged["means"]) if self.prune_near_cameras is not None else torch.zeros_like(prune)
        prune |= near | self.pruning(rows_from)
        kept = torch.nonzero(~prune).squeeze(1)
        gaussians.edit({name: value[kept] for name, value in merged.items()}, rows_from[kept], replace)
        log.debug("step %d: %d cloned, %d split, %d pruned (%d near the cameras): %d Gaussians", step, len(cloned), len(halves),
                  int(prune.sum()), int(near.sum()), len(kept))
        self.grad_sum = self.seen = None

    def growing(self, mean_grad: torch.Tensor) -> torch.Tensor:
        """(N,) bool: the Gaussians that grow at this refinement, from their (N,) mean screen-space gradients."""
        return mean_grad > self.grow_grad2d

    def pruning(self, rows_from: torch.Tensor) -> torch.Tensor:
        """(N_new,) bool: Gaussians pruned for reasons of a strategy's own, beside opacity, size and the cameras'
        near field, given each new row's old row (``rows_from``, -1 for a new one); none here."""
        return torch.zeros(rows_from.shape, dtype=torch.bool, device=rows_from.device)

    def near_few_cameras(self, means: torch.Tensor) -> torch.Tensor:
        """(N,) bool: the means within ``prune_near_cameras`` of the scene scale from a training camera's centre that
        fewer than ``near_cameras_min_views`` training views see (the class docstring)."""
        if self.cameras is None:
            raise ValueError("model.strategy.prune_near_cameras needs the training cameras, which the splat model gives "
                             "the strategy when training starts")
        K, c2w, height, width = self.cameras
        centres = c2w[:, :3, 3].to(means)
        near = torch.cdist(means, centres).amin(dim=-1) < self.prune_near_cameras * self.scene_scale
        rows = torch.nonzero(near).squeeze(1)  # only the near ones need their views counted
        few = views_seeing(means[rows], K, c2w, height, width) < self.near_cameras_min_views
        return torch.zeros_like(near).index_fill_(0, rows[few], True)

    def loss(self, gaussians: Gaussians) -> torch.Tensor | None:
        """No regulariser."""
        return None

    @torch.no_grad()
    def reset_opacities(self, gaussians: Gaussians, replace: Replace) -> None:
        logits = gaussians.opacity_logits.detach().clamp(max=inverse_sigmoid(2.0 * self.prune_opacity))
        fresh = torch.full((len(logits),), -1, dtype=torch.long, device=logits.device)  # their optimiser state starts again
        replace(gaussians, "opacity_logits", logits, fresh)


class ViewConsistentStrategy(DefaultStrategy):
    """3DGS's adaptive density control where the views agree (FastGS's multi-view consistent densification and
    pruning, Ren et al. 2026): a Gaussian grows only where several views find it under their errors, and one that
    draws almost nothing in any of them goes.

    At each refinement, ``views`` training views drawn at random are rendered; a view's high-error pixels are those
    whose L1 error (the mean over the colours) exceeds ``error_threshold`` of the view's largest. For each Gaussian the
    model measures, over those views, the mean of its blend weights on their high-error pixels (``high``, in pixels)
    and on all their pixels (``drawn``) (``score_views``, set by the splat model when training starts). Then

    - a Gaussian grows where the default strategy would (its mean screen-space gradient over ``grow_grad2d``) and
      ``high`` is at least ``grow_score``: a large gradient from one view that the others do not share (a floater
      seen from one side, noise) does not grow;
    - besides the default strategy's pruning, a Gaussian that some sampled view sees whose ``drawn`` is under
      ``prune_drawn`` (hidden behind others, or too faint to matter) goes.

    So the count stays near what the pictures need, and a step draws fewer Gaussians. Other arguments: as
    :class:`DefaultStrategy`'s.
    """

    def __init__(self, *args, views: int = 10, error_threshold: float = 0.1, grow_score: float = 1.0,
                 prune_drawn: float = 0.01, **kwargs) -> None:
        super().__init__(*args, **kwargs)
        if views < 1 or not 0.0 <= error_threshold < 1.0 or grow_score < 0.0 or prune_drawn < 0.0:
            raise ValueError(f"ViewConsistentStrategy needs views >= 1, 0 <= error_threshold < 1, grow_score >= 0 and "
                             f"prune_drawn >= 0, got {views}, {error_threshold}, {grow_score} and {prune_drawn}")
        self.views, self.error_threshold, self.grow_score, self.prune_drawn = views, error_threshold, grow_score, prune_drawn
        # (V,) training view indices, error_threshold -> (N,) high, (N,) drawn, (N,) bool seen: set by the model
        self.score_views: Callable[[torch.Tensor, float], tuple[torch.Tensor, torch.Tensor, torch.Tensor]] | None = None
        self._scores: tuple[torch.Tensor, torch.Tensor, torch.Tensor] | None = None

    @torch.no_grad()
    def refine(self, gaussians: Gaussians, step: int, replace: Replace) -> None:
        if self.score_views is None or self.cameras is None:
            raise ValueError("model/strategy=view_consistent needs the training views drawn and scored, which the splat "
                             "model sets up when training starts")
        count = len(self.cameras[1])
        picks = torch.randperm(count, generator=self.generator)[: min(self.views, count)]
        self._scores = self.score_views(picks, self.error_threshold)
        try:
            super().refine(gaussians, step, replace)
        finally:
            self._scores = None

    def growing(self, mean_grad: torch.Tensor) -> torch.Tensor:
        high = self._scores[0].to(mean_grad.device)
        return super().growing(mean_grad) & (high >= self.grow_score)

    def pruning(self, rows_from: torch.Tensor) -> torch.Tensor:
        _, drawn, seen = self._scores
        old = rows_from >= 0  # a new Gaussian (a clone, a split's child) has not been drawn yet
        faint = torch.zeros(rows_from.shape, dtype=torch.bool, device=rows_from.device)
        rows = rows_from[old]
        faint[old] = seen.to(rows.device)[rows] & (drawn.to(rows.device)[rows] < self.prune_drawn)
        return faint


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
