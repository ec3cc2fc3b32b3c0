"""nerfacto's proposal sampler (Mip-NeRF 360, nerfacc's ``PropNetEstimator``): small density networks decide, level by
level, where along each ray the field is sampled; they learn from the field's own weights through the interlevel loss."""

from __future__ import annotations

from collections.abc import Sequence

import torch
from torch import nn

from nerf_lightning.fields.base import Field
from nerf_lightning.geometry.space import Rays, SceneSpace
from nerf_lightning.rendering.samplers.base import RaySampler, RaySamples, sample_pdf
from nerf_lightning.rendering.volume import render_weights


def spacing(t: torch.Tensor) -> torch.Tensor:
    """nerfstudio's piecewise spacing s(t): t / 2 up to t = 1 (linear near the cameras), 1 - 1 / (2t) beyond (linear in
    disparity), so that s in [0, 1) covers all distances up to infinity."""
    return torch.where(t < 1.0, t / 2.0, 1.0 - 0.5 / t.clamp(min=1.0))


def spacing_inverse(s: torch.Tensor) -> torch.Tensor:
    """The inverse of :func:`spacing`: s in [0, 1) -> t."""
    return torch.where(s < 0.5, 2.0 * s, 0.5 / (1.0 - s).clamp(min=1e-6))


def initial_edges(t_enter: torch.Tensor, t_exit: torch.Tensor, n_samples: int, perturb: bool) -> torch.Tensor:
    """(N,) ray ranges -> (N, S + 1) edges evenly spaced in :func:`spacing` (uniform near, linear in disparity far),
    each interval jittered within itself when ``perturb`` (one shift a ray, as nerfstudio's ``single_jitter``)."""
    s_enter, s_exit = spacing(t_enter), spacing(t_exit)
    steps = torch.linspace(0.0, 1.0, n_samples + 1, device=t_enter.device, dtype=t_enter.dtype)
    if perturb:
        shift = (torch.rand_like(t_enter)[:, None] - 0.5) / n_samples
        steps = (steps + shift).clamp(0.0, 1.0)
    return spacing_inverse(s_enter[:, None] + (s_exit - s_enter)[:, None] * steps)


def interval_weights(density: torch.Tensor, edges: torch.Tensor) -> torch.Tensor:
    """(N, S) densities of the intervals between (N, S + 1) edges -> (N, S) volume-rendering weights."""
    return render_weights(density, edges[:, 1:] - edges[:, :-1])


def outer_weights(edges: torch.Tensor, env_edges: torch.Tensor, env_weights: torch.Tensor) -> torch.Tensor:
    """For each interval of ``edges`` (N, S + 1), the sum of the weights (N, P) of the intervals of ``env_edges``
    (N, P + 1) that overlap it: the most weight a coarser histogram allows there (Mip-NeRF 360's outer measure)."""
    cumulative = torch.cat([torch.zeros_like(env_weights[:, :1]), torch.cumsum(env_weights, dim=-1)], dim=-1)  # (N, P + 1)
    starts, ends = edges[:, :-1].contiguous(), edges[:, 1:].contiguous()
    low = (torch.searchsorted(env_edges[:, :-1].contiguous(), starts, right=True) - 1).clamp(0, env_weights.shape[1] - 1)
    high = torch.searchsorted(env_edges[:, 1:].contiguous(), ends, right=True).clamp(0, env_weights.shape[1] - 1)
    return torch.gather(cumulative[:, 1:], 1, high) - torch.gather(cumulative[:, :-1], 1, low)


def interlevel_loss(edges: torch.Tensor, weights: torch.Tensor, proposal_edges: torch.Tensor, proposal_weights: torch.Tensor) -> torch.Tensor:
    """Mip-NeRF 360's proposal loss: zero where the proposal's histogram bounds the field's (detached) weights, and
    max(w - bound, 0)^2 / w summed over a ray otherwise; the mean over the rays. edges (N, S + 1), weights (N, S);
    proposal_edges (N, P + 1), proposal_weights (N, P)."""
    edges, weights = edges.detach(), weights.detach()
    bound = outer_weights(edges, proposal_edges, proposal_weights)
    return ((weights - bound).clamp(min=0.0) ** 2 / (weights + 1e-7)).sum(dim=-1).mean()


def distortion_loss(edges: torch.Tensor, weights: torch.Tensor) -> torch.Tensor:
    """Mip-NeRF 360's distortion loss in linear time, the mean over N rays of

        sum_ij w_i w_j |m_i - m_j| + 1/3 sum_i w_i^2 (e_(i+1) - e_i)

    for interval edges e (N, S + 1) (sorted), midpoints m and weights w (N, S): the first sum, over sorted midpoints,
    is 2 sum_i w_i (m_i W_(<i) - (wm)_(<i)) with exclusive cumulative sums, instead of S^2 terms."""
    mids, widths = 0.5 * (edges[:, 1:] + edges[:, :-1]), edges[:, 1:] - edges[:, :-1]
    weight_before = torch.cumsum(weights, dim=-1) - weights
    moment_before = torch.cumsum(weights * mids, dim=-1) - weights * mids
    inter = 2.0 * (weights * (mids * weight_before - moment_before)).sum(dim=-1)
    intra = (weights**2 * widths).sum(dim=-1) / 3.0
    return (inter + intra).mean()


class ProposalSampler(RaySampler):
    """Proposal networks (nerfacto): an initial histogram of ``proposal_samples[0]`` intervals a ray, uniform near
    the cameras and linear in disparity beyond (:func:`initial_edges`); at each level a proposal network
    (a :class:`~nerf_lightning.fields.grid.DensityField`) gives the intervals' weights, and the next level's
    intervals are drawn from those weights (inverse CDF, :func:`sample_pdf`), down to ``field_samples`` intervals
    for the field.

    Training: the proposal weights are annealed, ``w ** a`` with a rising from 0 (uniform) to 1 over
    ``anneal_steps`` (nerfacto's schedule, slope ``anneal_slope``); the proposal networks get gradients every
    ``update_every`` steps (every step for the first ``warmup_steps``), and learn from :func:`interlevel_loss`
    (weight ``interlevel_weight``) against the field's detached weights. :func:`distortion_loss` (weight
    ``distortion_weight``) on the field's weights, in the spacing's [0, 1] coordinates, discourages floaters.

    Evaluation (no perturbation, no gradients): with ``bake_resolution`` set, each proposal network is first read off
    a grid of that many cells a side (:meth:`DensityField.bake <nerf_lightning.fields.grid.DensityField.bake>`, kept
    until its weights change), and the proposal levels interpolate that grid instead of running the network: most
    of an evaluation frame's points are proposal points, so a frame costs little more than the field's own samples.

    Args:
        proposal_fields: one density network a level (nerfacto: two).
        proposal_samples: intervals a ray at each level (nerfacto: 256, 96).
        field_samples: intervals a ray the field is evaluated on (nerfacto: 48).
        bake_resolution: None, or the cells a side of the grids the proposal networks are baked into for evaluation.
    """

    def __init__(
        self,
        proposal_fields: Sequence[nn.Module],
        proposal_samples: Sequence[int] = (256, 96),
        field_samples: int = 48,
        anneal_steps: int = 1000,
        anneal_slope: float = 10.0,
        update_every: int = 5,
        warmup_steps: int = 100,
        interlevel_weight: float = 1.0,
        distortion_weight: float = 0.002,
        padding: float = 0.01,
        bake_resolution: int | None = None,
    ) -> None:
        super().__init__()
        if len(proposal_fields) != len(proposal_samples) or not proposal_fields:
            raise ValueError(f"ProposalSampler needs one proposal field a level: {len(proposal_fields)} fields for "
                             f"proposal_samples={list(proposal_samples)}")
        if min(proposal_samples) < 1 or field_samples < 1 or update_every < 1:
            raise ValueError(f"ProposalSampler needs samples >= 1 and update_every >= 1, got {list(proposal_samples)}, {field_samples}, {update_every}")
        self.proposal_fields = nn.ModuleList(proposal_fields)
        self.proposal_samples, self.field_samples = [int(n) for n in proposal_samples], int(field_samples)
        self.anneal_steps, self.anneal_slope = anneal_steps, anneal_slope
        self.update_every, self.warmup_steps = update_every, warmup_steps
        self.interlevel_weight, self.distortion_weight = interlevel_weight, distortion_weight
        self.padding = padding
        if bake_resolution is not None and bake_resolution < 1:
            raise ValueError(f"ProposalSampler needs bake_resolution >= 1 or None, got {bake_resolution}")
        self.bake_resolution = bake_resolution
        self._bakes: dict[int, tuple[tuple, nn.Module]] = {}  # level -> (the weights it was baked from, the bake)
        # what a training step reads of the step count, set by update(): a compiled step (model.compile) reads a tensor
        # whose value changes and a flag of two values, not the count itself (a new constant each step: a new graph)
        self.learns = True
        self.register_buffer("exponent", torch.tensor(0.0), persistent=False)
        self.update(0, None)

    def update(self, step: int, field: Field | None) -> None:
        self.learns = step < self.warmup_steps or step % self.update_every == 0
        self.exponent_value = self.anneal(step)
        self.exponent.fill_(self.exponent_value)

    def anneal(self, step: int) -> float:
        """The exponent the proposal weights are raised to before resampling: 0 at step 0, 1 from ``anneal_steps`` on."""
        x = min(max(step / max(self.anneal_steps, 1), 0.0), 1.0)
        return (self.anneal_slope * x) / ((self.anneal_slope - 1.0) * x + 1.0)

    def baked(self, level: int) -> nn.Module:
        """Proposal network ``level`` baked at ``bake_resolution`` (made again once its weights have changed)."""
        proposal = self.proposal_fields[level]
        weights = tuple((p.data_ptr(), p._version) for p in proposal.parameters()) + (self.bake_resolution,)
        if self._bakes.get(level, (None,))[0] != weights:
            self._bakes[level] = (weights, proposal.bake(self.bake_resolution))
        return self._bakes[level][1]

    def sample(self, rays: Rays, space: SceneSpace, field: Field, perturb: bool) -> RaySamples:
        t_enter, t_exit = space.ray_range(rays)
        learn = perturb and torch.is_grad_enabled() and self.learns
        # compiled: the tensor (the graph outlives the step); plainly, the number (PyTorch raises to a number in its own
        # rounding, and the CPU presets keep their results bit for bit)
        exponent = (self.exponent if torch.compiler.is_compiling() else self.exponent_value) if perturb else 1.0
        # a module still training (the live viewer renders between steps) changes every step: a bake would not outlive the frame
        bake = self.bake_resolution is not None and not self.training and not perturb and not torch.is_grad_enabled()
        proposals = [self.baked(level) for level in range(len(self.proposal_fields))] if bake else self.proposal_fields
        edges, levels = None, []
        for proposal, n_samples in zip(proposals, self.proposal_samples):
            if edges is None:
                edges = initial_edges(t_enter, t_exit, n_samples, perturb)
            else:
                edges = sample_pdf(edges, levels[-1][1].detach() ** exponent, n_samples + 1, perturb, self.padding)
            mids = 0.5 * (edges[:, 1:] + edges[:, :-1])
            points = space.to_field(rays.origins[:, None, :] + rays.directions[:, None, :] * mids[..., None])
            with torch.set_grad_enabled(learn):
                weights = interval_weights(proposal.density(points).float(), edges)
            levels.append((edges, weights))
        edges = sample_pdf(edges, levels[-1][1].detach() ** exponent, self.field_samples + 1, perturb, self.padding)
        return RaySamples.from_edges(edges, field_edges=edges, proposal_levels=levels, proposal_learns=learn)

    def losses(self, samples: RaySamples, rendered: dict[str, torch.Tensor], target_rgb: torch.Tensor) -> dict[str, torch.Tensor]:
        edges = samples.extras["field_edges"]
        weights = rendered["weights"].reshape(samples.n_rays, -1)  # the field's, S intervals a ray
        losses = {}
        if samples.extras["proposal_learns"]:
            losses["interlevel"] = self.interlevel_weight * sum(
                interlevel_loss(edges, weights, level_edges, level_weights) for level_edges, level_weights in samples.extras["proposal_levels"])
        if self.distortion_weight > 0:
            losses["distortion"] = self.distortion_weight * distortion_loss(spacing(edges), weights)
        return losses

    def extra_repr(self) -> str:
        baked = f", bake_resolution={self.bake_resolution}" if self.bake_resolution is not None else ""
        return f"proposal_samples={self.proposal_samples}, field_samples={self.field_samples}, update_every={self.update_every}{baked}"
