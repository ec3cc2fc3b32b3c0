"""3D Gaussian splatting as Markov chain Monte Carlo (Kheradmand et al. 2024), a densification strategy
(:mod:`~nerf_lightning.splats.strategy` gives the interface): dead Gaussians relocated onto live ones drawn in proportion
to opacity, the count grown the same way to a cap, and noise shaped by each Gaussian's covariance moving the
transparent ones."""

from __future__ import annotations

import logging
import math

import torch

from nerf_lightning.splats.gaussians import PARAMETERS, Gaussians
from nerf_lightning.splats.projection import Projection, covariances
from nerf_lightning.splats.strategy import Replace

log = logging.getLogger(__name__)


class MCMCStrategy:
    """3D Gaussian splatting as Markov chain Monte Carlo (Kheradmand et al. 2024), with gsplat's ``MCMCStrategy``
    numbers: the Gaussians are samples of the scene's opacity, so none is pruned and none is split by a gradient
    threshold; instead

    - every ``refine_every`` steps from ``refine_start`` until ``refine_stop``, each dead Gaussian (opacity under
      ``min_opacity``) is moved onto a live one drawn in proportion to opacity (:meth:`relocate`), and then up to
      ``grow_rate`` - 1 more Gaussians (5%) are added the same way, the count never passing ``cap_max``
      (:meth:`grow`). A Gaussian drawn k times is shared by k + 1 copies with opacity and scales chosen so that
      they render as it did (:func:`relocation`), and the optimiser state of every row touched starts afresh;
    - every step, each mean moves by noise shaped by its own covariance, scaled by the means' learning rate times
      ``noise_lr`` and gated by ``sigmoid(-100 (opacity - 0.005))`` (:meth:`inject_noise`): transparent Gaussians
      wander (the chain explores), opaque ones stay where the views put them;
    - :meth:`loss` adds ``opacity_reg`` x the mean opacity and ``scale_reg`` x the mean scale, so that Gaussians the
      views do not need fade (and are relocated) and stay small.

    The count starts as the Gaussians start (the sparse points, or the random cloud) and only grows: ``cap_max``
    is the size the user wants, and memory is about 1 KB a Gaussian at SH degree 3 with its gradients and Adam state.

    Args:
        max_count, reset_every: :class:`DefaultStrategy`'s keys, taken so that an experiment written for it
            (``experiment=splat_procedural model/strategy=mcmc``) runs as it is: ``max_count`` caps the count too (the
            lower of it and ``cap_max`` holds); MCMC resets no opacities, so ``reset_every`` is not used.
    """

    # the noise's opacity gate sigmoid(-k (o - t)) (gsplat's op_sigmoid): about 1 under t, about 0 a few 1 / k above
    NOISE_K, NOISE_T = 100.0, 0.005
    absgrad = False  # it reads no screen-space statistics

    def __init__(self, cap_max: int = 1_000_000, noise_lr: float = 5e5, refine_start: int = 500, refine_stop: int = 25_000,
                 refine_every: int = 100, min_opacity: float = 0.005, grow_rate: float = 1.05, opacity_reg: float = 0.01,
                 scale_reg: float = 0.01, seed: int = 0, max_count: int | None = None, reset_every: int | None = None) -> None:
        if cap_max < 1 or grow_rate < 1.0 or refine_every < 1:
            raise ValueError(f"model.strategy needs cap_max >= 1, grow_rate >= 1 and refine_every >= 1, got {cap_max}, {grow_rate}, {refine_every}")
        self.cap_max = cap_max if max_count is None else min(cap_max, max_count)
        if max_count is not None and max_count < cap_max:
            log.info("MCMC: the Gaussians are capped at model.strategy.max_count = %d (under cap_max = %d)", max_count, cap_max)
        self.noise_lr, self.min_opacity, self.grow_rate = noise_lr, min_opacity, grow_rate
        self.refine_start, self.refine_stop, self.refine_every = refine_start, refine_stop, refine_every
        self.opacity_reg, self.scale_reg = opacity_reg, scale_reg
        self.scene_scale = 1.0  # set by the model; MCMC does not use it
        self.seed = seed
        self.generator = torch.Generator().manual_seed(seed)  # the draws of sources (on the CPU)
        self.noise_generator: torch.Generator | None = None  # the noise's, on the Gaussians' device (made at first use)

    def after_backward(self, gaussians: Gaussians, projection: Projection, width: int, height: int) -> None:
        """MCMC reads no screen-space statistics."""

    def after_step(self, gaussians: Gaussians, step: int, replace: Replace, means_lr: float) -> None:
        if self.refine_start <= step < self.refine_stop and step % self.refine_every == 0:
            relocated = self.relocate(gaussians, replace)
            added = self.grow(gaussians, replace)
            log.debug("step %d: %d relocated, %d added: %d Gaussians", step, relocated, added, len(gaussians))
        self.inject_noise(gaussians, means_lr)

    def loss(self, gaussians: Gaussians) -> torch.Tensor | None:
        """``opacity_reg`` x mean opacity + ``scale_reg`` x mean scale (gsplat's MCMC regularisers), or None if both are 0."""
        if (self.opacity_reg == 0 and self.scale_reg == 0) or len(gaussians) == 0:
            return None
        return self.opacity_reg * gaussians.opacities.mean() + self.scale_reg * torch.exp(gaussians.log_scales).mean()

    @torch.no_grad()
    def relocate(self, gaussians: Gaussians, replace: Replace) -> int:
        """Move every dead Gaussian (opacity < ``min_opacity``) onto a live one drawn in proportion to its opacity;
        the count stays. Returns how many moved."""
        values = {name: getattr(gaussians, name).detach().clone() for name in PARAMETERS}
        opacities = torch.sigmoid(values["opacity_logits"])
        dead = torch.nonzero(opacities < self.min_opacity).squeeze(1)
        alive = torch.nonzero(opacities >= self.min_opacity).squeeze(1)
        if len(dead) == 0 or len(alive) == 0:
            return 0
        sources = alive[draw_in_proportion(opacities[alive], len(dead), self.generator)]
        self.share(values, sources)
        for value in values.values():
            value[dead] = value[sources]
        rows_from = torch.arange(len(opacities), device=dead.device)
        rows_from[dead] = -1  # the moved rows and their sources start their optimiser state afresh
        rows_from[sources] = -1
        gaussians.edit(values, rows_from, replace)
        return len(dead)

    @torch.no_grad()
    def grow(self, gaussians: Gaussians, replace: Replace) -> int:
        """Add up to (``grow_rate`` - 1) x N Gaussians, never more than ``cap_max`` in all, each a copy of one drawn in
        proportion to its opacity. Returns how many were added."""
        n = len(gaussians)
        added = max(min(self.cap_max, int(self.grow_rate * n)) - n, 0)
        if added == 0:
            return 0
        values = {name: getattr(gaussians, name).detach().clone() for name in PARAMETERS}
        sources = draw_in_proportion(torch.sigmoid(values["opacity_logits"]), added, self.generator)
        self.share(values, sources)
        kept = torch.arange(n, device=sources.device)
        kept[sources] = -1  # the sources' opacity and scales changed: their optimiser state starts afresh, as the copies' do
        rows_from = torch.cat([kept, torch.full_like(sources, -1)])
        gaussians.edit({name: torch.cat([value, value[sources]]) for name, value in values.items()}, rows_from, replace)
        return added

    def share(self, values: dict[str, torch.Tensor], sources: torch.Tensor) -> None:
        """Give each of ``sources`` (R,) rows of ``values`` (a row may come more than once: k times, k + 1 copies
        of it will be) the opacity and scales of one of its copies (:func:`relocation`), in place."""
        copies = torch.bincount(sources, minlength=len(values["opacity_logits"]))[sources] + 1
        opacities, scales = relocation(torch.sigmoid(values["opacity_logits"][sources]), torch.exp(values["log_scales"][sources]),
                                       copies, self.min_opacity)
        values["opacity_logits"][sources] = torch.logit(opacities)
        values["log_scales"][sources] = torch.log(scales)

    @torch.no_grad()
    def inject_noise(self, gaussians: Gaussians, means_lr: float) -> None:
        """Move each mean by Sigma z, its covariance Sigma (N, 3, 3) times standard normal noise z (N, 3) (gsplat's:
        the covariance, not its square root, so the step is in the Gaussian's own shape and squared size), times
        ``means_lr`` x ``noise_lr`` x the opacity gate; in place, so the optimiser keeps the same parameter."""
        scale = means_lr * self.noise_lr
        if scale == 0 or len(gaussians) == 0:
            return
        g = gaussians
        device = g.means.device
        if self.noise_generator is None or self.noise_generator.device != device:
            self.noise_generator = torch.Generator(device=device).manual_seed(self.seed + 1)
        gate = torch.sigmoid(-self.NOISE_K * (g.opacities.detach() - self.NOISE_T))  # (N,)
        noise = torch.randn(g.means.shape, generator=self.noise_generator, device=device) * (scale * gate)[:, None]
        g.means.add_((covariances(g.quats.detach(), g.log_scales.detach()) @ noise[..., None])[..., 0])


# a Gaussian shared by more copies than this is shared as if by this many (gsplat's N_MAX: the table's size)
MAX_COPIES = 51
_SHARE_TABLES: dict[torch.device, torch.Tensor] = {}


def relocation(opacities: torch.Tensor, scales: torch.Tensor, copies: torch.Tensor,
               min_opacity: float = 0.005) -> tuple[torch.Tensor, torch.Tensor]:
    """The opacity and scales each of n copies of a Gaussian takes so that together they render as it did
    (Kheradmand et al. 2024, eq. 9; gsplat's relocation kernel): (R,) opacities o, (R, 3) scales s and (R,) long
    copies n (clamped to 1..``MAX_COPIES``) -> (R,) o' = 1 - (1 - o)^(1/n), so that n of them over one another
    are as opaque as the one, 1 - (1 - o')^n = o (o' is kept in [``min_opacity``, 1 - eps], which only a nearly
    transparent source feels), and (R, 3) s' = s o / D with

        D = sum_{i=1}^{n} sum_{k=0}^{i-1} C(i-1, k) (-1)^k o'^(k+1) / sqrt(k+1)
          = sum_{m=1}^{n} C(n, m) (-1)^(m-1) o'^m / sqrt(m)     (sum_{i=m}^{n} C(i-1, m-1) = C(n, m)),

    so that the copies' summed footprint matches the source's. In float32 throughout (the second form has n terms,
    not n (n + 1) / 2)."""
    n = copies.clamp(1, MAX_COPIES)
    eps = torch.finfo(opacities.dtype).eps
    new_opacities = (1.0 - torch.pow(1.0 - opacities, 1.0 / n.to(opacities.dtype))).clamp(min_opacity, 1.0 - eps)
    table = _SHARE_TABLES.get(opacities.device)
    if table is None:  # (MAX_COPIES + 1, MAX_COPIES): row n, column m - 1 holds C(n, m) (-1)^(m-1) / sqrt(m)
        rows = [[math.comb(row, m) * (-1) ** (m - 1) / math.sqrt(m) for m in range(1, MAX_COPIES + 1)] for row in range(MAX_COPIES + 1)]
        table = _SHARE_TABLES[opacities.device] = torch.tensor(rows, dtype=torch.float32).to(opacities.device)
    powers = new_opacities[:, None] ** torch.arange(1, MAX_COPIES + 1, device=opacities.device, dtype=opacities.dtype)  # (R, MAX_COPIES)
    denominators = (table[n] * powers).sum(dim=-1)
    return new_opacities, scales * (opacities / denominators)[:, None]


def draw_in_proportion(weights: torch.Tensor, count: int, generator: torch.Generator) -> torch.Tensor:
    """``count`` indices of ``weights`` (N,) (not all zero) drawn with replacement in proportion to them, on the
    weights' device; drawn on the CPU from ``generator``, past torch.multinomial's 2^24 categories by the inverse CDF."""
    cpu = weights.detach().float().cpu()
    if len(cpu) <= 2**24:
        drawn = torch.multinomial(cpu, count, replacement=True, generator=generator)
    else:
        cdf = torch.cumsum(cpu, dim=0)
        drawn = torch.searchsorted(cdf, torch.rand(count, generator=generator) * cdf[-1], right=True).clamp(max=len(cpu) - 1)
    return drawn.to(weights.device)
