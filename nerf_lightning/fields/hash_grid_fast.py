"""The hash-grid encoding's fast paths: :func:`~nerf_lightning.fields.hash_grid_reference.encode_reference`'s values, faster.

:func:`choose_path` picks one for a pass from the device, whether gradients are needed, F and the dtype;
:func:`encode` runs it. Two ways:

- ``compiled`` (a CPU, no gradients): the reference itself through ``torch.compile``. Eagerly, each of its
  operations is a pass through memory over all points; inductor fuses the rows, the gather and the weighted sum of
  the 8 corners into one loop over the points. With gradients it is not used: compiling a training step was not
  worth its compile time.
- the gather paths (everywhere else): all 8 corners of all levels at once as (2, 2, 2, L, M) tensors, the points
  innermost (what a CPU's vector units need); rows in int32 where no product can overflow it (half the bytes through
  the hashing); :func:`gather_rows`, whose backward adds every part's gradient into one buffer. On a CPU, rows of two
  floats (Instant-NGP's and nerfacto's F = 2) are gathered as single complex numbers (``complex_gather``), and in
  training the corners are summed as complex numbers too (``complex_sum``).
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Protocol

import torch

from nerf_lightning.compiling import CompiledOrEager
from nerf_lightning.fields.hash_grid_reference import cells_of, encode_reference



class HashGridEncoding(Protocol):
    """What the fast paths read of :class:`~nerf_lightning.fields.hash_grid.HashGridEncoding` (named here, so that
    the fast paths import nothing of the module that chooses them)."""

    resolutions: torch.Tensor  # (L,) each level's cells a side
    offsets: torch.Tensor  # (L,) each level's first row in the table
    corner_steps: torch.Tensor  # (2, 1, 1): a cell's lower and upper corner
    primes: tuple[int, ...]  # the spatial hash's three primes, modulo the table size
    index_dtype: torch.dtype
    n_levels: int
    n_dense: int  # the coarse levels stored densely, unhashed
    dense_rows: int  # their rows
    table_size: int
    features_per_level: int
    out_dim: int

    def read_table(self) -> torch.Tensor: ...

    def reference_inputs(self) -> tuple[torch.Tensor, ...]: ...

COMPILED, COMPLEX_SUM, COMPLEX_GATHER, GATHER = "compiled", "complex_sum", "complex_gather", "gather"
PATHS = (COMPILED, COMPLEX_SUM, COMPLEX_GATHER, GATHER)

# the one compiled function of the process (every encoding's: one compilation; a failing compiler warns once and
# leaves plain PyTorch)
compiled_reference = CompiledOrEager(encode_reference, "the hash grid's encoding")


def choose_path(device_type: str, grad_enabled: bool, features: int, dtype: torch.dtype, compile_evaluation: bool = True,
                n_points: int = 2) -> str:
    """The path for a pass over ``n_points`` points on a device of type ``device_type`` ("cpu", "cuda", "mps"), with
    or without gradients, of a table of rows of ``features`` values of ``dtype``:

    - ``compiled``: a CPU, no gradients, ``compile_evaluation``, more than one point (sizes 0 and 1 would compile anew);
    - ``complex_sum``: a CPU, gradients, rows of two float32 or float64: the complex product of the corners' weighted
      sum has no trailing axis of 2 to broadcast over, forward and backward;
    - ``complex_gather``: a CPU, no gradients (not compiled), rows of two floats: summed as real rows (without
      gradients the complex product was no faster);
    - ``gather``: the rest (a GPU, other widths and dtypes): real rows.
    """
    on_cpu = device_type == "cpu"
    if on_cpu and not grad_enabled and compile_evaluation and n_points > 1:
        return COMPILED
    if on_cpu and features == 2 and dtype in (torch.float32, torch.float64):
        return COMPLEX_SUM if grad_enabled else COMPLEX_GATHER
    return GATHER


def encode(path: str, encoding: HashGridEncoding, points: torch.Tensor) -> torch.Tensor:
    """(M, 3) points in [0, 1] -> (M, L * F), ``encoding``'s features through ``path`` (one of :data:`PATHS`)."""
    if path == COMPILED:
        # the table detached: a plain tensor, whose size the compiled code takes as a variable (torch.compile keeps a
        # parameter's sizes fixed, and would compile again for every table size: the proposal networks', the field's)
        table, *levels = encoding.reference_inputs()
        return compiled_reference(points, table.detach(), *levels)
    if path not in PATHS:
        raise ValueError(f"hash grid path must be one of {PATHS}, got {path!r}")
    return encode_gathered(encoding, points, complex_rows=path != GATHER, complex_sum=path == COMPLEX_SUM)


def encode_gathered(encoding: HashGridEncoding, points: torch.Tensor, complex_rows: bool, complex_sum: bool) -> torch.Tensor:
    """The gather paths: (M, 3) points -> (M, L * F), the dense levels and the hashed ones as two parts, the rows
    gathered as complex numbers (``complex_rows``; rows of two floats) and summed as complex numbers (``complex_sum``)."""
    lower, fraction = cells_of(points, encoding.resolutions)  # (3, L, M) each, the points innermost
    # trilinear weights (2, 2, 2, L, M), indexed by (dx, dy, dz): the product of (1 - f, f) along each axis
    w = torch.stack([1.0 - fraction, fraction])  # (2, 3, L, M)
    weights = w[:, None, None, 0] * w[None, :, None, 1] * w[None, None, :, 2]
    lower = lower.to(encoding.index_dtype)
    n_dense, n_levels = encoding.n_dense, encoding.n_levels
    parts = [(levels, hashed) for levels, hashed in ((slice(0, n_dense), False), (slice(n_dense, n_levels), True))
             if levels.start < levels.stop]
    rows = [corner_rows(encoding, lower[:, levels], hashed) for levels, hashed in parts]  # (2, 2, 2, n, M) each
    # each part's rows count from its own start in the table (the hashed levels' from dense_rows)
    starts = [encoding.dense_rows if hashed else 0 for _, hashed in parts]
    corner_features = gather_rows(encoding.read_table(), [part.reshape(-1) for part in rows], starts, complex_rows)
    features = []
    for (levels, _), part, found in zip(parts, rows, corner_features):
        corner_weights = weights[..., levels, :]  # (2, 2, 2, n, M)
        if complex_sum:
            found = torch.view_as_complex(found).view(part.shape)
            features.append(torch.view_as_real((corner_weights * found).sum(dim=(0, 1, 2))))  # (n, M, 2)
        else:
            found = found.view(*part.shape, encoding.features_per_level)
            features.append((corner_weights[..., None] * found).sum(dim=(0, 1, 2)))  # (n, M, F)
    features = torch.cat(features) if len(features) > 1 else features[0]  # (L, M, F)
    return features.transpose(0, 1).reshape(points.shape[0], encoding.out_dim)


def corner_rows(encoding: HashGridEncoding, lower: torch.Tensor, hashed: bool) -> torch.Tensor:
    """(3, n, M) integer lower corners of M points' cells, axis by axis, at the dense levels (``hashed=False``, the
    first ``n_dense``) or the hashed ones (the rest) -> (2, 2, 2, n, M) rows of those levels' part of the table
    (counted from the part's first row) of the cells' vertices, indexed by (dx, dy, dz). Each axis's two
    coordinates, (2, n, M), are combined by broadcasting over the leading axes."""
    steps, n_dense, offsets = encoding.corner_steps, encoding.n_dense, encoding.offsets
    if hashed:  # a hashed level's table is T rows from the part's start at level * T: its offset is an OR (= XOR)
        mask = encoding.table_size - 1
        x, y, z = (((lower[axis] + steps) * encoding.primes[axis]) & mask for axis in range(3))  # (2, n, M) each
        x = x ^ (offsets[n_dense:] - offsets[n_dense])[:, None]
        return (x[:, None] ^ y[None, :])[:, :, None] ^ z[None, None, :]
    side = (encoding.resolutions[:n_dense] + 1)[:, None]  # (n, 1)
    x, y, z = (lower[axis] + steps for axis in range(3))  # (2, n, M) each
    x = x + offsets[:n_dense, None]
    return (x[:, None] + y[None, :] * side)[:, :, None] + z[None, None, :] * (side * side)


def gather_rows(table: torch.Tensor, rows: Sequence[torch.Tensor], starts: Sequence[int],
                complex_rows: bool = False) -> list[torch.Tensor]:
    """Rows of a table in parts: (T, F) features, the parts' (K_i,) row indices, each counted from row ``starts[i]``
    -> each part's (K_i, F) features, ``table[starts[i]:][rows[i]]``, differentiable in ``table``.

    The backward adds every part's gradient into one (T, F) buffer: autograd, given one ``index_select`` a part, would
    make a zero buffer for each (the part's size), another of the whole table's size for a part taken as a slice of
    it, and add them up: fresh memory to zero and add.
    ``complex_rows`` (rows of two float32 or float64, on a CPU): each row is gathered and scattered as one complex
    element, the same values: PyTorch's CPU ``index_select`` and ``index_add_`` move one 8-byte element faster than
    a row of two floats."""
    if len(rows) != len(starts):
        raise ValueError(f"gather_rows expected a start for each part's rows, got {len(rows)} parts and {len(starts)} starts")
    return list(_GatherRows.apply(table, tuple(int(start) for start in starts), complex_rows, *rows))


class _GatherRows(torch.autograd.Function):
    """``gather_rows``: forward one ``index_select`` a part, backward one ``index_add_`` a part into one zero buffer."""

    @staticmethod
    def forward(ctx, table: torch.Tensor, starts: tuple[int, ...], complex_rows: bool,  # noqa: D102
                *rows: torch.Tensor) -> tuple[torch.Tensor, ...]:
        ctx.save_for_backward(*rows)
        ctx.set_materialize_grads(False)  # a part whose features go unused gets None, not a buffer of zeros to add
        ctx.starts, ctx.complex_rows, ctx.table_shape, ctx.table_dtype = starts, complex_rows, table.shape, table.dtype
        found = []
        for start, part in zip(starts, rows):
            if complex_rows:
                found.append(torch.view_as_real(torch.index_select(torch.view_as_complex(table[start:]), 0, part)))
            else:
                found.append(torch.index_select(table[start:], 0, part))
        return tuple(found)

    @staticmethod
    def backward(ctx, *grads: torch.Tensor | None) -> tuple[torch.Tensor | None, ...]:  # noqa: D102
        rows = ctx.saved_tensors
        grad_table = None
        if ctx.needs_input_grad[0]:
            grad_table = torch.zeros(ctx.table_shape, dtype=ctx.table_dtype, device=rows[0].device)
            for start, part, grad in zip(ctx.starts, rows, grads):
                if grad is not None:  # None: that part's features were not used
                    grad = grad.contiguous()
                    if ctx.complex_rows:
                        torch.view_as_complex(grad_table[start:]).index_add_(0, part, torch.view_as_complex(grad))
                    else:
                        grad_table[start:].index_add_(0, part, grad)
        return (grad_table, None, None, *(None for _ in rows))
