"""Instant-NGP's multiresolution hash encoding (Müller et al. 2022), in plain PyTorch.

Level ``l`` of ``L`` is a grid of ``N_l + 1`` vertices a side over the unit cube, with
``N_l = floor(N_min * b**l)`` and ``b`` chosen so that the last level has ``N_max`` cells a side. Each vertex
owns a learnt feature vector of ``F`` values, kept in a table of at most ``T`` rows for the level: coarse levels
that fit index their vertices densely (``x + y (N+1) + z (N+1)^2``), fine levels hash them,

    h(x, y, z) = (x * 1  XOR  y * 2654435761  XOR  z * 805459861)  mod T,

and let colliding vertices share a row (the MLP after it sorts collisions out). A point's feature at a level
is the trilinear interpolation of its cell's 8 vertex features; the output concatenates the levels.
"""

from __future__ import annotations

import math

import torch
from torch import nn

PRIMES = (1, 2654435761, 805459861)

# (8, 3) the corners of a cell, as 0/1 offsets
CORNERS = torch.tensor([[i >> 2 & 1, i >> 1 & 1, i & 1] for i in range(8)], dtype=torch.long)


def level_resolutions(n_levels: int, base_resolution: int, max_resolution: int) -> list[int]:
    """Cells a side N_l of each level: a geometric series from ``base_resolution`` to ``max_resolution``."""
    if n_levels == 1:
        return [base_resolution]
    growth = math.exp((math.log(max_resolution) - math.log(base_resolution)) / (n_levels - 1))
    return [int(math.floor(base_resolution * growth**level + 1e-6)) for level in range(n_levels)]


class HashGridEncoding(nn.Module):
    """Multiresolution hash encoding of points in the unit cube.

    Args:
        n_levels: L, the number of resolutions.
        features_per_level: F, the width of a vertex's feature.
        log2_table_size: log2 of T, the most rows a level's table has.
        base_resolution, max_resolution: cells a side of the coarsest and the finest level.
        init_scale: features start uniform in (-init_scale, init_scale), as in Instant-NGP.

    ``forward``: (..., 3) points in [0, 1] (clamped) -> (..., L * F), level by level.
    """

    def __init__(
        self,
        n_levels: int = 16,
        features_per_level: int = 2,
        log2_table_size: int = 19,
        base_resolution: int = 16,
        max_resolution: int = 2048,
        init_scale: float = 1e-4,
    ) -> None:
        super().__init__()
        if n_levels < 1 or features_per_level < 1 or not 1 <= base_resolution <= max_resolution:
            raise ValueError(
                f"HashGridEncoding needs n_levels >= 1, features_per_level >= 1 and 1 <= base_resolution <= max_resolution, "
                f"got {n_levels}, {features_per_level}, {base_resolution}, {max_resolution}"
            )
        self.n_levels, self.features_per_level = n_levels, features_per_level
        self.table_size = 2**log2_table_size
        resolutions = level_resolutions(n_levels, base_resolution, max_resolution)
        sizes = [min((n + 1) ** 3, self.table_size) for n in resolutions]
        self.register_buffer("resolutions", torch.tensor(resolutions, dtype=torch.long), persistent=False)
        self.register_buffer("hashed", torch.tensor([(n + 1) ** 3 > self.table_size for n in resolutions]), persistent=False)
        self.register_buffer("offsets", torch.tensor([0, *sizes[:-1]], dtype=torch.long).cumsum(0), persistent=False)
        # (sum of the levels' table sizes, F): every level's vertex features, one level after another
        self.table = nn.Parameter(torch.empty(sum(sizes), features_per_level).uniform_(-init_scale, init_scale))

    @property
    def out_dim(self) -> int:
        return self.n_levels * self.features_per_level

    def vertex_rows(self, x: torch.Tensor, y: torch.Tensor, z: torch.Tensor) -> torch.Tensor:
        """(M, L) integer vertex coordinates, level by level -> (M, L) rows of ``table``."""
        side = self.resolutions + 1  # (L,)
        dense = x + y * side + z * side * side
        hashed = torch.bitwise_xor(torch.bitwise_xor(x * PRIMES[0], y * PRIMES[1]), z * PRIMES[2]) & (self.table_size - 1)
        return torch.where(self.hashed, hashed, dense) + self.offsets

    def forward(self, points: torch.Tensor) -> torch.Tensor:
        """(..., 3) points in [0, 1] -> (..., L * F)"""
        if points.shape[-1] != 3:
            raise ValueError(f"HashGridEncoding expected (..., 3) points, got {tuple(points.shape)}")
        lead = points.shape[:-1]
        points = points.reshape(-1, 3).clamp(0.0, 1.0)
        scaled = points[:, None, :] * self.resolutions[:, None].to(points)  # (M, L, 3) in cell units
        lower = scaled.floor().long().clamp(max=(self.resolutions - 1)[:, None])  # the last cell keeps x = 1 inside
        fraction = scaled - lower  # (M, L, 3) in [0, 1]
        (x, y, z), (fx, fy, fz) = lower.unbind(-1), fraction.unbind(-1)
        rows, weights = [], []
        for cx, cy, cz in CORNERS.tolist():  # the cell's 8 vertices and their trilinear weights
            rows.append(self.vertex_rows(x + cx, y + cy, z + cz))
            weights.append((fx if cx else 1.0 - fx) * (fy if cy else 1.0 - fy) * (fz if cz else 1.0 - fz))
        rows_all, weights_all = torch.stack(rows, dim=-1), torch.stack(weights, dim=-1)  # (M, L, 8)
        # one gather for every level and corner, so backward scatters into the table once
        corner_features = torch.index_select(self.table, 0, rows_all.reshape(-1)).view(*rows_all.shape, self.features_per_level)
        features = (weights_all[..., None] * corner_features).sum(dim=-2)  # (M, L, F)
        return features.reshape(*lead, self.out_dim)
