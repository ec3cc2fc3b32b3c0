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

import itertools
import math
from collections.abc import Sequence

import torch
from torch import nn

from nerf_lightning.compiling import CompiledOrEager

PRIMES = (1, 2654435761, 805459861)


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
        compile_evaluation: on a CPU, without gradients (renders, evaluation, the viewer, and training's passes that
            need none), run the encoding through ``torch.compile`` (:func:`interpolate_corners`; a fern frame 1.5x
            faster on 2 cores, a fern training step 10 % faster; docs/benchmarks.md), falling back to plain PyTorch
            with a warning where this machine cannot compile.

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
        compile_evaluation: bool = True,
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
        # rows are computed in int32 where no product can overflow it: a hashed coordinate times a prime reduced
        # modulo T (the same row: only the low log2 T bits are kept) stays below (N_max + 1) (T - 1); on a CPU the
        # no-grad forward is then about 40 % faster (half the bytes through the hashing; docs/benchmarks.md)
        fits = (max(resolutions) + 1) * (self.table_size - 1) < 2**31 and sum(sizes) < 2**31
        self.index_dtype = torch.int32 if fits else torch.long
        self.primes = tuple(prime & (self.table_size - 1) for prime in PRIMES)
        self.register_buffer("resolutions", torch.tensor(resolutions, dtype=self.index_dtype), persistent=False)
        self.register_buffer("hashed", torch.tensor([(n + 1) ** 3 > self.table_size for n in resolutions]), persistent=False)
        # the levels whose vertices all fit their table come first (resolutions grow): they index densely
        self.n_dense = int((~self.hashed).sum())
        self.dense_rows = sum(sizes[: self.n_dense])  # where the hashed levels' rows start
        self.register_buffer("offsets", torch.tensor([0, *sizes[:-1]]).cumsum(0).to(self.index_dtype), persistent=False)
        # (2, 1, 1): a cell's lower and upper vertex along an axis, on the encoding's device
        self.register_buffer("corner_steps", torch.tensor([0, 1], dtype=self.index_dtype)[:, None, None], persistent=False)
        # (sum of the levels' table sizes, F): every level's vertex features, one level after another
        self.table = nn.Parameter(torch.empty(sum(sizes), features_per_level).uniform_(-init_scale, init_scale))
        self.compile_evaluation = compile_evaluation
        # interpolate_corners' hashing: the primes reduced modulo T and T - 1, as tensors (one compiled graph serves
        # every table size)
        self.register_buffer("hash_primes", torch.tensor(self.primes), persistent=False)
        self.register_buffer("hash_mask", torch.tensor(self.table_size - 1), persistent=False)

    @property
    def out_dim(self) -> int:
        return self.n_levels * self.features_per_level

    def corner_rows(self, lower: torch.Tensor, hashed: bool) -> torch.Tensor:
        """(3, n, M) integer lower corners of M points' cells, axis by axis, at the dense levels (``hashed=False``, the
        first ``n_dense``) or the hashed ones (the rest) -> (2, 2, 2, n, M) rows of those levels' part of ``table``
        (counted from the part's first row) of the cells' vertices, indexed by (dx, dy, dz). Each axis's two
        coordinates, (2, n, M), are combined by broadcasting over the leading axes, the points' axis innermost (what
        a CPU's vector units need)."""
        steps = self.corner_steps
        if hashed:  # a hashed level's table is T rows from the part's start at level * T: its offset is an OR (= XOR)
            mask = self.table_size - 1
            x, y, z = (((lower[axis] + steps) * self.primes[axis]) & mask for axis in range(3))  # (2, n, M) each
            x = x ^ (self.offsets[self.n_dense:] - self.offsets[self.n_dense])[:, None]
            return (x[:, None] ^ y[None, :])[:, :, None] ^ z[None, None, :]
        side = (self.resolutions[: self.n_dense] + 1)[:, None]  # (n, 1)
        x, y, z = (lower[axis] + steps for axis in range(3))  # (2, n, M) each
        x = x + self.offsets[: self.n_dense, None]
        return (x[:, None] + y[None, :] * side)[:, :, None] + z[None, None, :] * (side * side)

    def evaluates_compiled(self, points: torch.Tensor) -> bool:
        """Whether (M, 3) points go through the compiled :func:`interpolate_corners`: ``compile_evaluation``, without
        gradients (renders, validation, the viewer, meshes, the proposal networks' bakes; in training, the proposal
        networks' passes on the steps they do not learn and the occupancy grid's refreshes), on a CPU, more than one
        point (sizes 0 and 1 would compile anew)."""
        return (self.compile_evaluation and not torch.is_grad_enabled() and points.device.type == "cpu"
                and points.shape[0] > 1)

    def forward(self, points: torch.Tensor) -> torch.Tensor:
        """(..., 3) points in [0, 1] -> (..., L * F)"""
        if points.shape[-1] != 3:
            raise ValueError(f"HashGridEncoding expected (..., 3) points, got {tuple(points.shape)}")
        lead = points.shape[:-1]
        points = points.reshape(-1, 3).clamp(0.0, 1.0)
        if self.evaluates_compiled(points):
            # the table detached: a plain tensor, whose size the compiled code takes as a variable (torch.compile keeps
            # a parameter's sizes fixed, and would compile again for every table size: the proposal networks', the field's)
            features = _compiled_interpolation(points, self.table.detach(), self.resolutions, self.hashed, self.offsets,
                                               self.hash_primes, self.hash_mask)
            return features.reshape(*lead, self.out_dim)
        lower, fraction = cells_of(points, self.resolutions)  # (3, L, M) each, the points innermost
        # trilinear weights (2, 2, 2, L, M), indexed by (dx, dy, dz): the product of (1 - f, f) along each axis
        w = torch.stack([1.0 - fraction, fraction])  # (2, 3, L, M)
        weights = w[:, None, None, 0] * w[None, :, None, 1] * w[None, None, :, 2]
        lower = lower.to(self.index_dtype)
        parts = [(levels, hashed) for levels, hashed in ((slice(0, self.n_dense), False), (slice(self.n_dense, self.n_levels), True))
                 if levels.start < levels.stop]
        rows = [self.corner_rows(lower[:, levels], hashed) for levels, hashed in parts]  # (2, 2, 2, n, M) each
        # each part's rows count from its own start in the table (the hashed levels' from dense_rows)
        starts = [self.dense_rows if hashed else 0 for _, hashed in parts]
        corner_features = gather_rows(self.table, [part.reshape(-1) for part in rows], starts)
        features = []
        for (levels, _), part, found in zip(parts, rows, corner_features):
            corner_weights = weights[..., levels, :]  # (2, 2, 2, n, M)
            if _complex_rows(found) and torch.is_grad_enabled():
                # in training, rows of two as complex numbers, as gathered: the weighted sum's product has no trailing
                # axis of 2 to broadcast over; forward + backward 19 to 26 % faster for the CPU presets' field, 29 to
                # 39 % for a proposal grid, a training step 8 % (docs/benchmarks.md); the values and gradients are the
                # same. Without gradients the complex product was no faster: evaluation keeps the real one
                found = torch.view_as_complex(found).view(part.shape)
                features.append(torch.view_as_real((corner_weights * found).sum(dim=(0, 1, 2))))  # (n, M, 2)
            else:
                found = found.view(*part.shape, self.features_per_level)
                features.append((corner_weights[..., None] * found).sum(dim=(0, 1, 2)))  # (n, M, F)
        features = torch.cat(features) if len(features) > 1 else features[0]  # (L, M, F)
        return features.transpose(0, 1).reshape(*lead, self.out_dim)


def interpolate_corners(points: torch.Tensor, table: torch.Tensor, resolutions: torch.Tensor, hashed: torch.Tensor,
                        offsets: torch.Tensor, primes: torch.Tensor, mask: torch.Tensor) -> torch.Tensor:
    """The encoding one cell corner at a time, for ``torch.compile``: (M, 3) points in [0, 1] -> (M, L * F).

    ``HashGridEncoding``'s state: ``table`` (rows, F); the levels' (L,) ``resolutions`` N_l, ``hashed`` flags and
    first rows ``offsets``; the (3,) ``primes`` and the 0-d ``mask`` T - 1. The same values as the encoding's batched
    forward, which lays all 8 corners' rows, weights and features out as (8, L, M) tensors, each a pass through
    memory; written corner by corner, inductor fuses the rows, the gather and the weighted sum into one loop over
    the points (a fern frame's encoding 2.5x faster on 2 CPU cores: 3.6 against 8.9 s, docs/benchmarks.md). Eagerly it is
    about as fast as the batched forward."""
    lower, fraction = cells_of(points, resolutions)  # (3, L, M) each
    x, y, z = lower.long()  # (L, M) each
    side = resolutions.long()[:, None] + 1  # (L, 1) vertices a side
    hashed, first_rows = hashed[:, None], offsets.long()[:, None]  # (L, 1) each
    features = torch.zeros(*x.shape, table.shape[-1], dtype=table.dtype, device=table.device)  # (L, M, F)
    for dx, dy, dz in itertools.product((0, 1), repeat=3):
        cx, cy, cz = x + dx, y + dy, z + dz
        dense = cx + (cy + cz * side) * side
        hashed_rows = ((cx * primes[0]) ^ (cy * primes[1]) ^ (cz * primes[2])) & mask
        rows = torch.where(hashed, hashed_rows, dense) + first_rows  # (L, M)
        weight = ((fraction[0] if dx else 1.0 - fraction[0]) * (fraction[1] if dy else 1.0 - fraction[1])
                  * (fraction[2] if dz else 1.0 - fraction[2]))  # (L, M)
        features = features + weight[..., None] * table[rows]
    return features.transpose(0, 1).reshape(points.shape[0], features.shape[0] * features.shape[2])


def cells_of(points: torch.Tensor, resolutions: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """(M, 3) points in [0, 1], the levels' (L,) cells a side -> the lower corners of the points' cells and the points'
    fractions across them, (3, L, M) floats each in cell units, the points innermost."""
    resolutions = resolutions.to(points)[:, None]  # (L, 1)
    scaled = points.t()[:, None, :] * resolutions  # (3, L, M) in cell units
    lower = torch.minimum(scaled.floor(), resolutions - 1.0)  # the last cell keeps x = 1 inside
    return lower, scaled - lower  # fractions in [0, 1]


_compiled_interpolation = CompiledOrEager(interpolate_corners, "the hash grid's encoding")


def gather_rows(table: torch.Tensor, rows: Sequence[torch.Tensor], starts: Sequence[int]) -> list[torch.Tensor]:
    """Rows of a table in parts: (T, F) features, the parts' (K_i,) row indices, each counted from row ``starts[i]``
    -> each part's (K_i, F) features, ``table[starts[i]:][rows[i]]``, differentiable in ``table``.

    The backward adds every part's gradient into one (T, F) buffer. Autograd, given one ``index_select`` a part, would
    make a zero buffer for each (the part's size), another of the whole table's size for a part taken as a slice of
    it, and add them up: fresh memory to zero and add, a ``nerfacto_forward_cpu`` training step on a CPU 3 to 12 %
    slower (docs/benchmarks.md).
    On a CPU, rows of two float32 (Instant-NGP's and nerfacto's F = 2) are gathered and scattered as single complex64
    elements: PyTorch's CPU ``index_select`` and ``index_add`` move one 8-byte element a row faster than a row of two
    floats (the encoding's forward + backward 11 to 25 % faster). The values are the same."""
    if len(rows) != len(starts):
        raise ValueError(f"gather_rows expected a start for each part's rows, got {len(rows)} parts and {len(starts)} starts")
    return list(_GatherRows.apply(table, tuple(int(start) for start in starts), *rows))


def _complex_rows(table: torch.Tensor) -> bool:
    """Whether (T, F) rows are gathered (and summed in training) as complex elements: rows of two floats on a CPU."""
    return table.device.type == "cpu" and table.shape[-1] == 2 and table.dtype in (torch.float32, torch.float64)


def _as_elements(table: torch.Tensor) -> torch.Tensor:
    """(T, F) -> the tensor whose dim-0 elements are gathered: (T,) complex64/128 for rows of two floats on a CPU."""
    return torch.view_as_complex(table) if _complex_rows(table) else table


class _GatherRows(torch.autograd.Function):
    """``gather_rows``: forward one ``index_select`` a part, backward one ``index_add_`` a part into one zero buffer."""

    @staticmethod
    def forward(ctx, table: torch.Tensor, starts: tuple[int, ...], *rows: torch.Tensor) -> tuple[torch.Tensor, ...]:  # noqa: D102
        ctx.save_for_backward(*rows)
        ctx.set_materialize_grads(False)  # a part whose features go unused gets None, not a buffer of zeros to add
        ctx.starts, ctx.table_shape, ctx.table_dtype = starts, table.shape, table.dtype
        found = []
        for start, part in zip(starts, rows):
            gathered = torch.index_select(_as_elements(table[start:]), 0, part)
            found.append(torch.view_as_real(gathered) if gathered.is_complex() else gathered)
        return tuple(found)

    @staticmethod
    def backward(ctx, *grads: torch.Tensor | None) -> tuple[torch.Tensor | None, ...]:  # noqa: D102
        rows = ctx.saved_tensors
        grad_table = None
        if ctx.needs_input_grad[0]:
            grad_table = torch.zeros(ctx.table_shape, dtype=ctx.table_dtype, device=rows[0].device)
            for start, part, grad in zip(ctx.starts, rows, grads):
                if grad is not None:  # None: that part's features were not used
                    elements = _as_elements(grad_table[start:])
                    grad = grad.contiguous()
                    elements.index_add_(0, part, torch.view_as_complex(grad) if elements.is_complex() else grad)
        return (grad_table, None, *(None for _ in rows))
