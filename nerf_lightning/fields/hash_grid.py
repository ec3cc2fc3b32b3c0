"""Instant-NGP's multiresolution hash encoding (Müller et al. 2022), in plain PyTorch.

Level ``l`` of ``L`` is a grid of ``N_l + 1`` vertices a side over the unit cube, with
``N_l = floor(N_min * b**l)`` and ``b`` chosen so that the last level has ``N_max`` cells a side. Each vertex
owns a learnt feature vector of ``F`` values, kept in a table of at most ``T`` rows for the level: coarse levels
that fit index their vertices densely (``x + y (N+1) + z (N+1)^2``), fine levels hash them,

    h(x, y, z) = (x * 1  XOR  y * 2654435761  XOR  z * 805459861)  mod T,

and let colliding vertices share a row (the MLP after it sorts collisions out). A point's feature at a level
is the trilinear interpolation of its cell's 8 vertex features; the output concatenates the levels.

This file is the reference: :func:`encode_reference` computes exactly that, one corner at a time.
:class:`HashGridEncoding` gets the same values through a faster path of :mod:`nerf_lightning.fields.hash_grid_fast`
(chosen there, for the device and for whether gradients are needed); tests hold each path equal to the reference.
"""

from __future__ import annotations

import itertools
import math

import torch
from torch import nn

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


class HashGridEncoding(nn.Module):
    """Multiresolution hash encoding of points in the unit cube.

    Args:
        n_levels: L, the number of resolutions.
        features_per_level: F, the width of a vertex's feature.
        log2_table_size: log2 of T, the most rows a level's table has.
        base_resolution, max_resolution: cells a side of the coarsest and the finest level.
        init_scale: features start uniform in (-init_scale, init_scale), as in Instant-NGP.
        compile_evaluation: on a CPU, without gradients (renders, evaluation, the viewer, and training's passes that
            need none), run the encoding through ``torch.compile`` (faster: one fused loop over the points), falling
            back to plain PyTorch with a warning where this machine cannot compile.
        table_precision: None (float32), ``float16`` or ``bfloat16``: the table read in that precision, half the
            bytes through the gather and the gradient's scatter (Instant-NGP keeps its table in float16), its
            float32 values kept for the optimiser. For GPUs: a CPU's float16 gathers and scatters are slower.

    ``forward``: (..., 3) points in [0, 1] (clamped) -> (..., L * F), level by level, through the path that
    :func:`~nerf_lightning.fields.hash_grid_fast.choose_path` picks; ``forward_reference``: the same through
    :func:`encode_reference`.
    """

    def __init__(
        self,
        n_levels: int = 16,
        features_per_level: int = 2,
        log2_table_size: int = 19,
        base_resolution: int = 16,
        max_resolution: int = 2048,
        init_scale: float = 1e-4,
        compile_evaluation: bool = True,
        table_precision: str | None = None,
    ) -> None:
        super().__init__()
        if table_precision not in (None, "float16", "bfloat16"):
            raise ValueError(f"model.field.encoding.table_precision must be null, float16 or bfloat16, got {table_precision!r}")
        self.table_precision = None if table_precision is None else getattr(torch, table_precision)
        if n_levels < 1 or features_per_level < 1 or not 1 <= base_resolution <= max_resolution:
            raise ValueError(
                f"HashGridEncoding needs n_levels >= 1, features_per_level >= 1 and 1 <= base_resolution <= max_resolution, "
                f"got {n_levels}, {features_per_level}, {base_resolution}, {max_resolution}"
            )
        self.n_levels, self.features_per_level = n_levels, features_per_level
        self.table_size = 2**log2_table_size
        resolutions = level_resolutions(n_levels, base_resolution, max_resolution)
        sizes = [min((n + 1) ** 3, self.table_size) for n in resolutions]
        # the fast paths compute rows in int32 where no product can overflow it (half the bytes through the hashing):
        # a hashed coordinate times a prime reduced modulo T stays below (N_max + 1) (T - 1)
        fits = (max(resolutions) + 1) * (self.table_size - 1) < 2**31 and sum(sizes) < 2**31
        self.index_dtype = torch.int32 if fits else torch.long
        self.primes = tuple(prime & (self.table_size - 1) for prime in PRIMES)  # modulo T: the same rows
        self.register_buffer("resolutions", torch.tensor(resolutions, dtype=self.index_dtype), persistent=False)
        self.register_buffer("hashed", torch.tensor([(n + 1) ** 3 > self.table_size for n in resolutions]), persistent=False)
        self.register_buffer("offsets", torch.tensor([0, *sizes[:-1]]).cumsum(0).to(self.index_dtype), persistent=False)
        self.register_buffer("hash_primes", torch.tensor(self.primes), persistent=False)
        self.register_buffer("hash_mask", torch.tensor(self.table_size - 1), persistent=False)
        # the levels whose vertices all fit their table come first (resolutions grow): they index densely
        self.n_dense = int((~self.hashed).sum())
        self.dense_rows = sum(sizes[: self.n_dense])  # where the hashed levels' rows start
        # (2, 1, 1): a cell's lower and upper vertex along an axis, on the encoding's device (the gather paths')
        self.register_buffer("corner_steps", torch.tensor([0, 1], dtype=self.index_dtype)[:, None, None], persistent=False)
        # (sum of the levels' table sizes, F): every level's vertex features, one level after another
        self.table = nn.Parameter(torch.empty(sum(sizes), features_per_level).uniform_(-init_scale, init_scale))
        self.compile_evaluation = compile_evaluation

    @property
    def out_dim(self) -> int:
        return self.n_levels * self.features_per_level

    def reference_inputs(self) -> tuple[torch.Tensor, ...]:
        """:func:`encode_reference`'s arguments after the points: the table (:meth:`read_table`) and the levels."""
        return self.read_table(), self.resolutions, self.hashed, self.offsets, self.hash_primes, self.hash_mask

    def read_table(self) -> torch.Tensor:
        """The (rows, F) table as the encoding reads it: the parameter, or a copy in ``table_precision`` (the
        parameter stays float32 for the optimiser; the gradient is added up in that precision, then cast back)."""
        return self.table if self.table_precision is None else self.table.to(self.table_precision)

    def _flat_points(self, points: torch.Tensor) -> torch.Tensor:
        if points.shape[-1] != 3:
            raise ValueError(f"HashGridEncoding expected (..., 3) points, got {tuple(points.shape)}")
        return points.reshape(-1, 3).clamp(0.0, 1.0)

    def forward(self, points: torch.Tensor) -> torch.Tensor:
        """(..., 3) points in [0, 1] -> (..., L * F)"""
        flat = self._flat_points(points)
        if torch.compiler.is_compiling():  # inside a compiled training step: inductor fuses the reference, forward and backward
            return encode_reference(flat, *self.reference_inputs()).reshape(*points.shape[:-1], self.out_dim)
        path = hash_grid_fast.choose_path(flat.device.type, torch.is_grad_enabled(), self.features_per_level,
                                          self.table_precision or self.table.dtype, self.compile_evaluation, flat.shape[0])
        return hash_grid_fast.encode(path, self, flat).reshape(*points.shape[:-1], self.out_dim)

    def forward_reference(self, points: torch.Tensor) -> torch.Tensor:
        """``forward`` through :func:`encode_reference`: the values every fast path must give."""
        flat = self._flat_points(points)
        return encode_reference(flat, *self.reference_inputs()).reshape(*points.shape[:-1], self.out_dim)


# last: the fast paths build on this file's reference (a circular import, resolved once the names above exist)
from nerf_lightning.fields import hash_grid_fast  # noqa: E402
