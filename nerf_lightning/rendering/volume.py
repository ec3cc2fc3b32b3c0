"""Discrete volume rendering (NeRF's quadrature) of dense rays: N rays of S samples each, no hidden state.

A ray crosses S intervals of lengths delta_i (units of the ray direction's length) with constant density sigma_i
and colour c_i inside each; the weights w_i are :mod:`nerf_lightning.rendering.compositing`'s (the maths is stated
there), and C = sum_i w_i c_i + (1 - sum_i w_i) background.

Every function is differentiable in density and colour.
"""

from __future__ import annotations

import torch

from nerf_lightning.rendering.compositing import weights_from_optical_depth


def transmittance(density: torch.Tensor, deltas: torch.Tensor) -> torch.Tensor:
    """Exclusive transmittance T_i: (..., S) densities and interval lengths -> (..., S), T_0 = 1."""
    return weights_from_optical_depth(density * deltas).transmittance


def render_weights(density: torch.Tensor, deltas: torch.Tensor) -> torch.Tensor:
    """Weights w_i = T_i (1 - exp(-sigma_i delta_i)): (..., S) -> (..., S); they sum to the accumulation <= 1."""
    return weights_from_optical_depth(density * deltas).weights


def composite(
    rgb: torch.Tensor,
    density: torch.Tensor,
    t: torch.Tensor,
    deltas: torch.Tensor,
    background: torch.Tensor | None = None,
) -> dict[str, torch.Tensor]:
    """Render rays from their samples.

    Args:
        rgb: (N, S, 3) colours of the samples.
        density: (N, S) non-negative densities.
        t: (N, S) distances of the samples along the rays.
        deltas: (N, S) lengths of the intervals the samples stand for.
        background: (3,) colour blended in by 1 - accumulation; None for none (black).

    Returns:
        ``rgb`` (N, 3); ``depth`` (N,) the expected distance at which the ray ends, given that it ends (the
        weighted mean of t; ``near``-side value where nothing is hit is meaningless, mask by accumulation);
        ``accumulation`` (N,) the opacity sum of weights; ``weights`` (N, S).
    """
    weights = render_weights(density, deltas)
    accumulation = weights.sum(dim=-1)
    colour = (weights[..., None] * rgb).sum(dim=-2)
    if background is not None:
        colour = colour + (1.0 - accumulation)[..., None] * background.to(colour)
    depth = (weights * t).sum(dim=-1) / accumulation.clamp(min=1e-10)
    return {"rgb": colour, "depth": depth, "accumulation": accumulation, "weights": weights}
