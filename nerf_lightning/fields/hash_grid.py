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

# (2,) a cell's lower and upper vertex along an axis
CORNER_STEPS = torch.tensor([0, 1], dtype=torch.long)


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
        # the levels whose vertices all fit their table come first (resolutions grow): they index densely
        self.n_dense = int((~self.hashed).sum())
        self.dense_rows = sum(sizes[: self.n_dense])  # where the hashed levels' rows start
        self.register_buffer("offsets", torch.tensor([0, *sizes[:-1]], dtype=torch.long).cumsum(0), persistent=False)
        # (sum of the levels' table sizes, F): every level's vertex features, one level after another
        self.table = nn.Parameter(torch.empty(sum(sizes), features_per_level).uniform_(-init_scale, init_scale))

    @property
    def out_dim(self) -> int:
        return self.n_levels * self.features_per_level

    def corner_rows(self, lower: torch.Tensor, hashed: bool) -> torch.Tensor:
        """(M, n, 3) integer lower corners of the points' cells at the dense levels (``hashed=False``, the first
        ``n_dense``) or the hashed ones (the rest) -> (M, n, 8) rows of those levels' part of ``table`` (counted from
        the part's first row) of the cells' 8 vertices, corner ``4 dx + 2 dy + dz``. Each axis's two coordinates are
        worked out once, (M, n, 2), and combined by broadcasting."""
        steps = CORNER_STEPS.to(lower.device)
        if hashed:  # a hashed level's table is T rows from the part's start at level * T: its offset is an OR (= XOR)
            mask = self.table_size - 1
            x, y, z = (((lower[..., axis, None] + steps) * PRIMES[axis]) & mask for axis in range(3))
            x = x ^ self.offsets[self.n_dense:, None] - self.offsets[self.n_dense]
            rows = (x[..., :, None] ^ y[..., None, :])[..., None] ^ z[..., None, None, :]
        else:
            side = (self.resolutions[: self.n_dense] + 1)[:, None]  # (n, 1)
            x, y, z = (lower[..., axis, None] + steps for axis in range(3))  # (M, n, 2) each
            x = x + self.offsets[: self.n_dense, None]
            rows = (x[..., :, None] + y[..., None, :] * side[..., None])[..., None] + z[..., None, None, :] * (side * side)[..., None, None]
        return rows.reshape(*lower.shape[:2], 8)

    def forward(self, points: torch.Tensor) -> torch.Tensor:
        """(..., 3) points in [0, 1] -> (..., L * F)"""
        if points.shape[-1] != 3:
            raise ValueError(f"HashGridEncoding expected (..., 3) points, got {tuple(points.shape)}")
        lead = points.shape[:-1]
        points = points.reshape(-1, 3).clamp(0.0, 1.0)
        scaled = points[:, None, :] * self.resolutions[:, None].to(points)  # (M, L, 3) in cell units
        lower = torch.minimum(scaled.floor(), (self.resolutions - 1)[:, None].to(points))  # the last cell keeps x = 1 inside
        fraction = scaled - lower  # (M, L, 3) in [0, 1]
        # trilinear weights, corner 4 dx + 2 dy + dz: the product of (1 - f, f) along each axis
        w = torch.stack([1.0 - fraction, fraction], dim=-1)  # (M, L, 3, 2)
        weights = (w[:, :, 0, :, None, None] * w[:, :, 1, None, :, None] * w[:, :, 2, None, None, :]).reshape(*w.shape[:2], 1, 8)
        lower = lower.long()
        features = []
        for levels, hashed in ((slice(0, self.n_dense), False), (slice(self.n_dense, self.n_levels), True)):
            if levels.start == levels.stop:
                continue
            rows = self.corner_rows(lower[:, levels], hashed)  # (M, n, 8)
            table = self.table[self.dense_rows:] if hashed else self.table  # the part the rows count from
            corner_features = torch.index_select(table, 0, rows.reshape(-1)).view(*rows.shape, self.features_per_level)
            with torch.autocast(points.device.type, enabled=False):  # the interpolation stays float32 under mixed precision
                features.append(torch.matmul(weights[:, levels], corner_features).squeeze(-2))  # (M, n, F)
        return torch.cat(features, dim=1).reshape(*lead, self.out_dim)
