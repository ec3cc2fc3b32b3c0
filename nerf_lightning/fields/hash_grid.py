"""The multiresolution hash encoding as a module (:class:`HashGridEncoding`, Instant-NGP, Müller et al. 2022): its
table and sizes, and the choice of how to evaluate it. The encoding as defined is
:func:`~nerf_lightning.fields.hash_grid_reference.encode_reference`; the faster paths that give the same values are in
:mod:`~nerf_lightning.fields.hash_grid_fast`, picked for the device and for whether gradients are needed
(:func:`~nerf_lightning.fields.hash_grid_fast.choose_path`). The three import one way: reference <- fast paths <- this
module.
"""

from __future__ import annotations

import torch
from torch import nn

from nerf_lightning.fields import hash_grid_fast
# the reference's names, also read from here (HashGridEncoding's users and earlier code import them from this module)
from nerf_lightning.fields.hash_grid_reference import PRIMES, cells_of, encode_reference, level_resolutions

__all__ = ["PRIMES", "HashGridEncoding", "cells_of", "encode_reference", "level_resolutions"]


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
