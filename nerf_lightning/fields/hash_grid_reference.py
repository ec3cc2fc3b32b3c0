"""Instant-NGP's multiresolution hash encoding (Müller et al. 2022), in plain PyTorch.

Level ``l`` of ``L`` is a grid of ``N_l + 1`` vertices a side over the unit cube, with
``N_l = floor(N_min * b**l)`` and ``b`` chosen so that the last level has ``N_max`` cells a side. Each vertex
owns a learnt feature vector of ``F`` values, kept in a table of at most ``T`` rows for the level: coarse levels
that fit index their vertices densely (``x + y (N+1) + z (N+1)^2``), fine levels hash them,

    h(x, y, z) = (x * 1  XOR  y * 2654435761  XOR  z * 805459861)  mod T,

and let colliding vertices share a row (the MLP after it sorts collisions out). A point's feature at a level
is the trilinear interpolation of its cell's 8 vertex features; the output concatenates the levels.

This file is the reference: :func:`encode_reference` computes exactly that, one corner at a time. The fast paths
(:mod:`~nerf_lightning.fields.hash_grid_fast`) build on it, and :class:`~nerf_lightning.fields.hash_grid.HashGridEncoding`
picks between them; tests hold each path equal to the reference.
"""

from __future__ import annotations

import itertools
import math

import torch

PRIMES = (1, 2654435761, 805459861)


def level_resolutions(n_levels: int, base_resolution: int, max_resolution: int) -> list[int]:
    """Cells a side N_l of each level: a geometric series from ``base_resolution`` to ``max_resolution``."""
    if n_levels == 1:
        return [base_resolution]
    growth = math.exp((math.log(max_resolution) - math.log(base_resolution)) / (n_levels - 1))
    return [int(math.floor(base_resolution * growth**level + 1e-6)) for level in range(n_levels)]


def cells_of(points: torch.Tensor, resolutions: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """(M, 3) points in [0, 1], the levels' (L,) cells a side -> the lower corners of the points' cells and the points'
    fractions across them, (3, L, M) floats each in cell units, the points innermost."""
    resolutions = resolutions.to(points)[:, None]  # (L, 1)
    scaled = points.t()[:, None, :] * resolutions  # (3, L, M) in cell units
    lower = torch.minimum(scaled.floor(), resolutions - 1.0)  # the last cell keeps x = 1 inside
    return lower, scaled - lower  # fractions in [0, 1]


def encode_reference(points: torch.Tensor, table: torch.Tensor, resolutions: torch.Tensor, hashed: torch.Tensor,
                     offsets: torch.Tensor, primes: torch.Tensor, mask: torch.Tensor) -> torch.Tensor:
    """The encoding as defined, one cell corner at a time: (M, 3) points in [0, 1] -> (M, L * F).

    ``table``: (rows, F), every level's rows one level after another. Per level, (L,) each: ``resolutions`` N_l,
    ``hashed`` (whether its (N_l + 1)^3 vertices outnumber the T rows it may have) and ``offsets`` (its first row).
    ``primes``: (3,) :data:`PRIMES` modulo T and ``mask``: T - 1, 0-d (``HashGridEncoding.reference_inputs()`` gives
    them all). The primes reduced modulo T give the same rows (only the low log2 T bits are kept); they and T are
    tensors, not numbers, so that ``torch.compile`` makes one graph for every table size. Differentiable in ``table``
    and ``points``."""
    lower, fraction = cells_of(points, resolutions)  # (3, L, M) each
    x, y, z = lower.long()  # (L, M) each
    side = resolutions.long()[:, None] + 1  # (L, 1) vertices a side
    hashed, first_rows = hashed[:, None], offsets.long()[:, None]  # (L, 1) each
    features = torch.zeros(*x.shape, table.shape[-1], dtype=table.dtype, device=table.device)  # (L, M, F)
    for dx, dy, dz in itertools.product((0, 1), repeat=3):  # the cell's 8 corners
        cx, cy, cz = x + dx, y + dy, z + dz
        dense = cx + (cy + cz * side) * side
        hashed_rows = ((cx * primes[0]) ^ (cy * primes[1]) ^ (cz * primes[2])) & mask  # mod T: T is a power of 2
        rows = torch.where(hashed, hashed_rows, dense) + first_rows  # (L, M)
        weight = ((fraction[0] if dx else 1.0 - fraction[0]) * (fraction[1] if dy else 1.0 - fraction[1])
                  * (fraction[2] if dz else 1.0 - fraction[2]))  # (L, M)
        features = features + weight[..., None] * table[rows]
    return features.transpose(0, 1).reshape(points.shape[0], features.shape[0] * features.shape[2])
