"""Compositing weights, written once: every renderer (dense rows, packed samples, rounds, splats) calls these.

A ray crosses samples i = 0, 1, ... in order. Sample i stands for an interval of length delta_i with density sigma_i
(its optical depth tau_i = sigma_i delta_i), or directly for an opacity alpha_i (a Gaussian splat). Then

    alpha_i = 1 - exp(-tau_i)                                   the chance the ray ends at sample i, if it gets there
    T_i     = prod_{j<i} (1 - alpha_j) = exp(-sum_{j<i} tau_j)  its transmittance: the chance it gets there (T_0 = 1)
    w_i     = T_i alpha_i                                       the chance it ends at sample i
    C       = sum_i w_i c_i + (1 - sum_i w_i) background         the accumulation sum_i w_i = 1 - T_after <= 1

A ray rendered in rounds (:class:`~nerf_lightning.rendering.rounds.RoundsRenderer`) carries its transmittance from
one round to the next: ``transmittance_before`` multiplies every T_i of the round, and ``transmittance_after`` is
what the ray leaves the round with, T_before prod_i (1 - alpha_i).

From densities the sums run over optical depths; from alphas over log(1 - alpha_i) = log1p(-alpha_i), so T is the
product of the (1 - alpha_j) and w_i is T_i alpha_i with the alpha given. That needs alpha_i < 1 (log(0) = -inf and
its gradient 1 / (1 - alpha) is infinite): a primitive that can be opaque clamps its alpha, as splats do at 0.999.

Dense rows (..., S) sum along the last dimension; packed samples (M,) carry ``ray_indices`` (M,), non-decreasing
(a ray's samples contiguous and in order), and ``n_rays`` N. Everything is differentiable in tau (or alpha) and in
``transmittance_before``.
"""

from __future__ import annotations

from typing import NamedTuple

import torch


class Compositing(NamedTuple):
    """What compositing a set of rays gives, for samples of shape (..., S) dense or (M,) packed, and rays (...,) or (N,).

    Attributes:
        weights: w_i = T_i alpha_i, per sample.
        transmittance: T_i, exclusive (what reaches sample i, times ``transmittance_before``), per sample.
        alpha: alpha_i, per sample (the input, from alpha).
        transmittance_after: per ray, what leaves its last sample: T_before prod_i (1 - alpha_i) = T_before - sum_i w_i.
    """

    weights: torch.Tensor
    transmittance: torch.Tensor
    alpha: torch.Tensor
    transmittance_after: torch.Tensor


def weights_from_optical_depth(optical_depth: torch.Tensor, transmittance_before: torch.Tensor | None = None) -> Compositing:
    """Dense rows: (..., S) optical depths tau_i = sigma_i delta_i >= 0 -> :class:`Compositing` of (..., S) and (...,).

    ``transmittance_before`` (...,): what each row arrives with from an earlier round; None for 1.

    The exclusive sum is the inclusive cumsum less the term (no zeros concatenated in front: one pass fewer in the
    renderer's round loop). In float32 that costs T_i a relative error of about 6e-8 sum_{j<=i} tau_j, sample i's
    own tau included: below 1e-5 unless that one sample has an optical depth over about 100 (opaque many times over).
    """
    _check_rows(optical_depth, transmittance_before)
    return _rows(optical_depth, 1.0 - torch.exp(-optical_depth), transmittance_before)


def weights_from_alpha(alpha: torch.Tensor, transmittance_before: torch.Tensor | None = None) -> Compositing:
    """Dense rows: (..., S) opacities 0 <= alpha_i < 1 -> :class:`Compositing` of (..., S) and (...,).

    ``transmittance_before`` (...,): what each row arrives with from an earlier round; None for 1.
    """
    _check_rows(alpha, transmittance_before)
    return _rows(_optical_depth_of(alpha), alpha, transmittance_before)


def weights_from_optical_depth_packed(
    optical_depth: torch.Tensor, ray_indices: torch.Tensor, n_rays: int, transmittance_before: torch.Tensor | None = None
) -> Compositing:
    """Packed samples: (M,) optical depths >= 0 of N rays -> :class:`Compositing` of (M,) and (N,).

    ``ray_indices`` (M,) non-decreasing; ``transmittance_before`` (N,), None for 1. A ray without samples leaves
    with the transmittance it came with. Sums restart at every ray (:func:`exclusive_sum_packed`).
    """
    _check_packed(optical_depth, ray_indices, n_rays, transmittance_before)
    return _packed(optical_depth, 1.0 - torch.exp(-optical_depth), ray_indices, n_rays, transmittance_before)


def weights_from_alpha_packed(
    alpha: torch.Tensor, ray_indices: torch.Tensor, n_rays: int, transmittance_before: torch.Tensor | None = None
) -> Compositing:
    """Packed samples: (M,) opacities 0 <= alpha_i < 1 of N rays -> :class:`Compositing` of (M,) and (N,).

    ``ray_indices`` (M,) non-decreasing; ``transmittance_before`` (N,), None for 1.
    """
    _check_packed(alpha, ray_indices, n_rays, transmittance_before)
    return _packed(_optical_depth_of(alpha), alpha, ray_indices, n_rays, transmittance_before)


def exclusive_sum_packed(values: torch.Tensor, ray_indices: torch.Tensor, n_rays: int) -> torch.Tensor:
    """(M,) values -> (M,) the sum of the earlier values of the same ray (0 for a ray's first sample).

    Each ray's values are laid out in a row of an (N, longest ray) table and summed along the row, so every sum
    restarts at its ray and adds up only that ray's values: float32 is as exact as the values themselves (a
    running sum over the whole batch, less each ray's start, loses the small terms of later rays to the large total).
    """
    return _exclusive_and_total_packed(values, ray_indices, n_rays)[0]


def _optical_depth_of(alpha: torch.Tensor) -> torch.Tensor:
    """-log(1 - alpha); an alpha of 1 (or rounding to it) is taken as 1 - 1e-6 here, so that the transmittance after
    it is tiny instead of NaN (checking would make a GPU wait on the host)."""
    return -torch.log1p(-alpha.clamp(max=1.0 - 1e-6))


def _rows(optical_depth: torch.Tensor, alpha: torch.Tensor, transmittance_before: torch.Tensor | None) -> Compositing:
    """The dense maths: (..., S) tau and alpha (consistent: alpha = 1 - exp(-tau)) -> :class:`Compositing`."""
    if optical_depth.shape[-1] == 0:
        after = optical_depth.new_ones(optical_depth.shape[:-1]) if transmittance_before is None else transmittance_before
        return Compositing(torch.zeros_like(alpha), torch.zeros_like(alpha), alpha, after)
    inclusive = optical_depth.cumsum(dim=-1)
    transmittance = torch.exp(optical_depth - inclusive)
    after = torch.exp(-inclusive[..., -1])
    if transmittance_before is not None:
        transmittance = transmittance_before[..., None] * transmittance
        after = transmittance_before * after
    return Compositing(transmittance * alpha, transmittance, alpha, after)


def _packed(
    optical_depth: torch.Tensor, alpha: torch.Tensor, ray_indices: torch.Tensor, n_rays: int, transmittance_before: torch.Tensor | None
) -> Compositing:
    """The packed maths: (M,) tau and alpha -> :class:`Compositing`."""
    exclusive, total = _exclusive_and_total_packed(optical_depth, ray_indices, n_rays)
    transmittance, after = torch.exp(-exclusive), torch.exp(-total)
    if transmittance_before is not None:
        transmittance = transmittance_before[ray_indices] * transmittance
        after = transmittance_before * after
    return Compositing(transmittance * alpha, transmittance, alpha, after)


# the columns of the table a ray's sums are laid out in (a power of two: a sample's row and column are a shift and a
# mask of its rank): a longer ray takes several rows, whose totals are summed the same way one level up, so the table
# stays about the size of the samples however long the longest ray
ROW_SHIFT = 5
ROW_LENGTH = 1 << ROW_SHIFT


def _exclusive_and_total_packed(values: torch.Tensor, ray_indices: torch.Tensor, n_rays: int) -> tuple[torch.Tensor, torch.Tensor]:
    """(M,) values -> (M,) exclusive sums within each ray (:func:`exclusive_sum_packed`) and (N,) each ray's total
    (0 for a ray without samples).

    Each ray's values fill rows of :data:`ROW_LENGTH` columns (a ray of 70 samples: three rows), every row is summed
    along itself, and the rows' totals are summed within their ray by the same function, one level up: every sum adds
    up values of one ray only, so float32 is as exact as the values themselves."""
    if values.numel() == 0:
        return values.clone(), values.new_zeros(n_rays)
    counts = torch.bincount(ray_indices, minlength=n_rays)
    rank = torch.arange(values.shape[0], device=values.device) - (torch.cumsum(counts, 0) - counts).index_select(0, ray_indices)
    longest = int(counts.max())
    if longest <= ROW_LENGTH:
        sums = values.new_zeros(n_rays, longest + 1).index_put((ray_indices, rank + 1), values).cumsum(dim=1)
        return sums.view(-1).index_select(0, ray_indices * (longest + 1) + rank), sums[:, -1]
    rows_per_ray = (counts + ROW_LENGTH - 1) >> ROW_SHIFT  # (N,)
    first_row = torch.cumsum(rows_per_ray, 0) - rows_per_ray
    row = first_row.index_select(0, ray_indices) + (rank >> ROW_SHIFT)  # (M,) the rows of a ray contiguous, in order
    cell = row * (ROW_LENGTH + 1) + (rank & (ROW_LENGTH - 1))  # (M,) where in the flattened table its sum lands
    n_rows = int(rows_per_ray.sum())
    sums = values.new_zeros(n_rows * (ROW_LENGTH + 1)).index_put((cell + 1,), values).view(n_rows, ROW_LENGTH + 1).cumsum(dim=1)
    row_ray = torch.repeat_interleave(torch.arange(n_rays, device=values.device), rows_per_ray, output_size=n_rows)
    before_row, total = _exclusive_and_total_packed(sums[:, -1], row_ray, n_rays)
    return sums.view(-1).index_select(0, cell) + before_row.index_select(0, row), total


def _check_rows(values: torch.Tensor, transmittance_before: torch.Tensor | None) -> None:
    if values.dim() < 1:
        raise ValueError(f"compositing dense rows needs samples of shape (..., S), got {tuple(values.shape)}")
    if transmittance_before is not None and transmittance_before.shape != values.shape[:-1]:
        raise ValueError(f"compositing rows of shape (..., S) = {tuple(values.shape)} needs transmittance_before of shape "
                         f"(...,) = {tuple(values.shape[:-1])}, got {tuple(transmittance_before.shape)}")


def _check_packed(values: torch.Tensor, ray_indices: torch.Tensor, n_rays: int, transmittance_before: torch.Tensor | None) -> None:
    if values.dim() != 1 or ray_indices.shape != values.shape:
        raise ValueError(f"compositing packed samples needs values (M,) and ray_indices (M,), "
                         f"got {tuple(values.shape)} and {tuple(ray_indices.shape)}")
    if transmittance_before is not None and transmittance_before.shape != (n_rays,):
        raise ValueError(f"compositing packed samples of {n_rays} rays needs transmittance_before of shape ({n_rays},), "
                         f"got {tuple(transmittance_before.shape)}")
