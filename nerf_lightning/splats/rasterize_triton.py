"""The rasteriser's GPU fast path: footprints binned into tiles and composited by Triton kernels, forward and
backward, as 3D Gaussian splatting and gsplat do it in CUDA.

The same values and gradients as :func:`~nerf_lightning.splats.rasterize_reference.rasterize_reference` (the tests hold
them equal), without a tensor of (footprint, pixel) pairs, and the same steps as the CPU's
:mod:`~nerf_lightning.splats.rasterize_tiles`:

1. **Binning** (:func:`bin_footprints`, PyTorch on the device): the footprints sorted nearest first (a stable sort,
   ties by index, as the reference's), packed a row each in that order; each lists the ``TILE`` x ``TILE`` tiles its
   pixel box touches (one ``repeat_interleave``), and one stable sort by tile leaves every tile's list nearest first.
2. **Forward** (``_composite``): a program a tile, a lane a pixel. The tile takes its footprints nearest first, one at
   a time for all its pixels: alpha = min(0.999, o exp(-sigma)), pairs under 1/255 skipped, a pixel done before the
   footprint that would take its transmittance to 1e-4 or below; the tile stops when all its pixels are done. Each
   pixel keeps its last transmittance and the tile-list position where it stopped.
3. **Backward** (``_composite_backward``): each tile walks its list back to front from the saved transmittance
   (T_i = T_i+1 / (1 - alpha_i)), carrying the weighted gradient sum of the footprints behind, so that
   d loss / d alpha_i = T_i g_i - (sum_{j > i} w_j g_j) / (1 - alpha_i). A footprint's gradient from one tile is
   summed over the tile's pixels (a reduction of fixed shape) into the footprint's own slot, beside the sums of the
   absolute values of each pixel's pull on its centre (``means2d.absgrad``); ``_sum_slots`` then adds a footprint's
   slots in tile order. No two programs add into one number (no atomics), so the same input gives the same gradients
   bit for bit.

Transmittance, the per-pixel sums, the sum behind and a tile's gradient sums are carried in float64 (a pixel may take
hundreds of footprints, and the backward pass divides by 1 - alpha; the tests hold the gradients to 1e-5, which float32
sums miss), the outputs and the slots' sums in float32 (float64 for float64 inputs). float64 runs at half float32's
rate on data-centre GPUs and far slower on consumer ones, but a step's time goes elsewhere (docs/benchmarks.md).
Triton compiles the kernels for the GPU the first time they run; on CPU tensors they run in Triton's interpreter
(numpy), which is how the tests check them without a GPU: far too slow to draw with, so
:mod:`~nerf_lightning.splats.draw` takes this path on CUDA only.

The kernels run through the autograd function all tile rasterisers share (:data:`TRITON_TILES`:
:class:`~nerf_lightning.splats.rasterize_core.TileComposite`) and read the packed rows' columns by the names
:mod:`~nerf_lightning.splats.rasterize_core` gives them.
"""

from __future__ import annotations

import os

import torch
import triton
import triton.language as tl

from nerf_lightning.splats.projection import MAX_ALPHA, MIN_ALPHA, MIN_TRANSMITTANCE, Projection
from nerf_lightning.splats.rasterize_core import (BOX_COLUMN, CONIC_COLUMN, FADE_COLUMN, FEATURE_COLUMN, FEATURES,
                                                  GRAD_ABSOLUTE, GRAD_CONIC, GRAD_FEATURES, GRAD_MEANS2D, GRAD_OPACITY,
                                                  GRADIENTS, MEANS2D_COLUMN, OPACITY_COLUMN, PACKED, TILE, TileKernels,
                                                  composite_features)

# the packed row's and the gradient row's columns as the kernels read and write them (Triton reads module constants
# only where they are constexpr)
_MEANS2D, _CONIC, _OPACITY = tl.constexpr(MEANS2D_COLUMN), tl.constexpr(CONIC_COLUMN), tl.constexpr(OPACITY_COLUMN)
_FEATURE, _BOX = tl.constexpr(FEATURE_COLUMN), tl.constexpr(BOX_COLUMN)
_G_MEANS2D, _G_CONIC, _G_OPACITY = tl.constexpr(GRAD_MEANS2D), tl.constexpr(GRAD_CONIC), tl.constexpr(GRAD_OPACITY)
_G_FEATURES, _G_ABSOLUTE = tl.constexpr(GRAD_FEATURES), tl.constexpr(GRAD_ABSOLUTE)
# footprints a program of _sum_slots adds up
SUM_BLOCK = 128


@triton.jit
def _footprint(packed, entries, k, u, v, PACKED: tl.constexpr):
    """Tile-list entry k's footprint at the pixel centres (u, v): dx, dy, sigma, whether each pixel is in its box,
    its conic (a, b, c), opacity o and features f0..f3 (colour and depth)."""
    footprint = packed + tl.load(entries + k).to(tl.int64) * PACKED
    mx, my = tl.load(footprint + _MEANS2D), tl.load(footprint + _MEANS2D + 1)
    a, b, c = tl.load(footprint + _CONIC), tl.load(footprint + _CONIC + 1), tl.load(footprint + _CONIC + 2)
    o = tl.load(footprint + _OPACITY)
    f0, f1 = tl.load(footprint + _FEATURE), tl.load(footprint + _FEATURE + 1)
    f2, f3 = tl.load(footprint + _FEATURE + 2), tl.load(footprint + _FEATURE + 3)
    in_box = (u >= tl.load(footprint + _BOX)) & (u <= tl.load(footprint + _BOX + 1) + 1.0) \
        & (v >= tl.load(footprint + _BOX + 2)) & (v <= tl.load(footprint + _BOX + 3) + 1.0)
    dx = u - mx
    dy = v - my
    sigma = 0.5 * (a * dx * dx + c * dy * dy) + b * dx * dy
    return dx, dy, sigma, in_box, a, b, c, o, f0, f1, f2, f3


@triton.jit
def _composite(packed, offsets, entries, height, width, tiles_x, shaded, accumulation, transmittance, stop,
               TILE: tl.constexpr, PACKED: tl.constexpr, MAX_ALPHA: tl.constexpr, MIN_ALPHA: tl.constexpr,
               MIN_TRANSMITTANCE: tl.constexpr):
    """Forward: one program a tile. Written: shaded (H * W, 4), accumulation, transmittance (H * W,) and stop (H * W,)
    int64, the tile-list position where the pixel was done (its tile's end where it never was)."""
    t = tl.program_id(0)
    lane = tl.arange(0, TILE * TILE)
    column = (t % tiles_x) * TILE + lane % TILE
    row = (t // tiles_x) * TILE + lane // TILE
    inside = (column < width) & (row < height)
    u = column.to(packed.dtype.element_ty) + 0.5
    v = row.to(packed.dtype.element_ty) + 0.5
    start = tl.load(offsets + t)
    end = tl.load(offsets + t + 1)
    left = tl.full([TILE * TILE], 1.0, tl.float64)
    s0 = tl.zeros([TILE * TILE], tl.float64)
    s1 = tl.zeros([TILE * TILE], tl.float64)
    s2 = tl.zeros([TILE * TILE], tl.float64)
    s3 = tl.zeros([TILE * TILE], tl.float64)
    weights = tl.zeros([TILE * TILE], tl.float64)
    ends = tl.zeros([TILE * TILE], tl.int64) + end
    active = inside
    k = start
    go = start < end
    while go:
        _, _, sigma, in_box, _, _, _, o, f0, f1, f2, f3 = _footprint(packed, entries, k, u, v, PACKED)
        alpha = tl.minimum(o * tl.exp(-sigma), MAX_ALPHA)
        take = active & in_box & (sigma >= 0.0) & (alpha >= MIN_ALPHA)
        alpha = alpha.to(tl.float64)
        after = left * (1.0 - alpha)
        finish = take & (after <= MIN_TRANSMITTANCE)
        ends = tl.where(finish, k, ends)
        active = active & (finish == 0)
        use = take & (finish == 0)
        weight = tl.where(use, alpha * left, 0.0)
        s0 += weight * f0
        s1 += weight * f1
        s2 += weight * f2
        s3 += weight * f3
        weights += weight
        left = tl.where(use, after, left)
        k += 1
        go = (k < end) & (tl.max(active.to(tl.int32), axis=0) > 0)
    pixel = row * width + column
    tl.store(shaded + pixel * 4 + 0, s0.to(packed.dtype.element_ty), mask=inside)
    tl.store(shaded + pixel * 4 + 1, s1.to(packed.dtype.element_ty), mask=inside)
    tl.store(shaded + pixel * 4 + 2, s2.to(packed.dtype.element_ty), mask=inside)
    tl.store(shaded + pixel * 4 + 3, s3.to(packed.dtype.element_ty), mask=inside)
    tl.store(accumulation + pixel, weights.to(packed.dtype.element_ty), mask=inside)
    tl.store(transmittance + pixel, left, mask=inside)
    tl.store(stop + pixel, ends, mask=inside)


@triton.jit
def _composite_backward(packed, offsets, entries, slot_of, height, width, tiles_x, transmittance, stop, grad_shaded,
                        grad_accumulation, slot_grads, TILE: tl.constexpr, PACKED: tl.constexpr,
                        GRADIENTS: tl.constexpr, MAX_ALPHA: tl.constexpr, MIN_ALPHA: tl.constexpr):
    """Backward: one program a tile, back to front. Written: slot_grads (E, GRADIENTS), at each tile-list entry's slot
    (``slot_of``), its footprint's gradient from this tile's pixels: d means2d (2), d conic (3), d opacity, d features
    (4), and the sums of the absolute values of each pixel's d means2d (2). Entries past every pixel's stop keep the
    zeros they were given."""
    t = tl.program_id(0)
    lane = tl.arange(0, TILE * TILE)
    column = (t % tiles_x) * TILE + lane % TILE
    row = (t // tiles_x) * TILE + lane // TILE
    inside = (column < width) & (row < height)
    pixel = row * width + column
    u = column.to(packed.dtype.element_ty) + 0.5
    v = row.to(packed.dtype.element_ty) + 0.5
    start = tl.load(offsets + t)
    ends = tl.load(stop + pixel, mask=inside, other=0)
    left = tl.load(transmittance + pixel, mask=inside, other=1.0)
    g0 = tl.load(grad_shaded + pixel * 4 + 0, mask=inside, other=0.0)
    g1 = tl.load(grad_shaded + pixel * 4 + 1, mask=inside, other=0.0)
    g2 = tl.load(grad_shaded + pixel * 4 + 2, mask=inside, other=0.0)
    g3 = tl.load(grad_shaded + pixel * 4 + 3, mask=inside, other=0.0)
    g4 = tl.load(grad_accumulation + pixel, mask=inside, other=0.0)
    behind = tl.zeros([TILE * TILE], tl.float64)  # sum over the footprints behind of w_j g_j
    last = tl.max(tl.where(inside, ends, start), axis=0)  # no pixel took a footprint from here on
    for j in range(0, last - start):
        k = last - 1 - j
        dx, dy, sigma, in_box, a, b, c, o, f0, f1, f2, f3 = _footprint(packed, entries, k, u, v, PACKED)
        falloff = tl.exp(-sigma)
        alpha = tl.minimum(o * falloff, MAX_ALPHA)
        take = inside & in_box & (k < ends) & (sigma >= 0.0) & (alpha >= MIN_ALPHA)
        if tl.max(take.to(tl.int32), axis=0) > 0:  # else the slot keeps its zeros: no pixel here drew it
            alpha64 = alpha.to(tl.float64)  # a name of its own: both branches of the if keep their types
            keep = 1.0 / (1.0 - alpha64)
            before = left * keep
            weight = alpha64 * before
            grad_weight = g4 + g0 * f0 + g1 * f1 + g2 * f2 + g3 * f3
            grad_alpha = before * grad_weight - behind * keep
            behind += tl.where(take, weight * grad_weight, 0.0)
            left = tl.where(take, before, left)
            unclamped = take & (o * falloff <= MAX_ALPHA)  # the clamp passes no gradient
            grad_sigma = tl.where(unclamped, -alpha64 * grad_alpha, 0.0)
            x, y = dx.to(tl.float64), dy.to(tl.float64)
            slot = slot_grads + tl.load(slot_of + k) * GRADIENTS
            pull_x = grad_sigma * (a * x + b * y)
            pull_y = grad_sigma * (c * y + b * x)
            tl.store(slot + _G_MEANS2D, -tl.sum(pull_x, axis=0))
            tl.store(slot + _G_MEANS2D + 1, -tl.sum(pull_y, axis=0))
            tl.store(slot + _G_CONIC, tl.sum(grad_sigma * 0.5 * x * x, axis=0))
            tl.store(slot + _G_CONIC + 1, tl.sum(grad_sigma * x * y, axis=0))
            tl.store(slot + _G_CONIC + 2, tl.sum(grad_sigma * 0.5 * y * y, axis=0))
            tl.store(slot + _G_OPACITY, tl.sum(tl.where(unclamped, falloff * grad_alpha, 0.0), axis=0))
            drawn = tl.where(take, weight, 0.0)
            tl.store(slot + _G_FEATURES, tl.sum(drawn * g0, axis=0))
            tl.store(slot + _G_FEATURES + 1, tl.sum(drawn * g1, axis=0))
            tl.store(slot + _G_FEATURES + 2, tl.sum(drawn * g2, axis=0))
            tl.store(slot + _G_FEATURES + 3, tl.sum(drawn * g3, axis=0))
            tl.store(slot + _G_ABSOLUTE, tl.sum(tl.abs(pull_x), axis=0))
            tl.store(slot + _G_ABSOLUTE + 1, tl.sum(tl.abs(pull_y), axis=0))


@triton.jit
def _sum_slots(slot_grads, first_slot, n_slots, out, n_footprints, BLOCK: tl.constexpr, GRADIENTS: tl.constexpr):
    """out (M, GRADIENTS): footprint i's gradient, the sum of its n_slots[i] slots from first_slot[i] on, in tile
    order."""
    i = tl.program_id(0) * BLOCK + tl.arange(0, BLOCK)
    valid = i < n_footprints
    first = tl.load(first_slot + i, mask=valid, other=0)
    count = tl.load(n_slots + i, mask=valid, other=0)
    gradient = tl.arange(0, 16)  # a power of two that holds GRADIENTS
    useful = gradient < GRADIENTS
    total = tl.zeros([BLOCK, 16], slot_grads.dtype.element_ty)
    for j in range(0, tl.max(count, axis=0)):
        taken = (j < count)[:, None] & useful[None, :]
        total += tl.load(slot_grads + (first + j)[:, None] * GRADIENTS + gradient[None, :], mask=taken, other=0.0)
    tl.store(out + i[:, None] * GRADIENTS + gradient[None, :], total, mask=valid[:, None] & useful[None, :])


def kernels(device_type: str) -> tuple:
    """The three kernels for tensors on ``device_type``: Triton compiles them for a GPU; CPU tensors run in Triton's
    interpreter over numpy, which the environment must ask for before Triton is imported (TRITON_INTERPRET=1, as the
    tests do)."""
    if device_type == "cpu" and os.environ.get("TRITON_INTERPRET") != "1":
        raise RuntimeError("the Triton rasteriser draws GPU tensors; CPU ones only in Triton's interpreter "
                           "(TRITON_INTERPRET=1 before triton is imported); on a CPU use model/rasterizer=tiles")
    return _composite, _composite_backward, _sum_slots


def bin_footprints(packed: torch.Tensor, tiles_x: int, tiles_y: int) -> tuple[torch.Tensor, ...]:
    """The footprints ``packed`` (M, PACKED) in drawing order, listed tile by tile.

    Returns ``offsets`` (T + 1,) int64 (tile t's footprints are ``entries[offsets[t]:offsets[t + 1]]``), ``entries``
    (E,) int32 rows of ``packed``, ``slot_of`` (E,) int64 where each entry's gradient goes, and ``first_slot`` (M,)
    and ``n_slots`` (M,) int64: a row's slots are ``first_slot[i]`` and the ``n_slots[i] - 1`` after it, in tile
    order. One stable sort by tile of the rows' (row, tile) pairs, listed row by row, keeps every tile nearest first."""
    device = packed.device
    boxes = packed[:, BOX_COLUMN:BOX_COLUMN + 4].long()  # first and last column, first and last row
    drawn = (boxes[:, 1] >= boxes[:, 0]) & (boxes[:, 3] >= boxes[:, 2])
    tile_x0, tile_y0 = boxes[:, 0].div(TILE, rounding_mode="floor"), boxes[:, 2].div(TILE, rounding_mode="floor")
    across = boxes[:, 1].div(TILE, rounding_mode="floor") - tile_x0 + 1
    down = boxes[:, 3].div(TILE, rounding_mode="floor") - tile_y0 + 1
    n_slots = torch.where(drawn, across * down, 0)
    first_slot = n_slots.cumsum(0) - n_slots
    n_entries = int(n_slots.sum())  # the one value read back a view: the lists' length
    rows = torch.repeat_interleave(torch.arange(len(packed), device=device), n_slots, output_size=n_entries)
    within = torch.arange(n_entries, device=device) - first_slot.index_select(0, rows)
    across_row = across.index_select(0, rows)
    tile = (tile_y0.index_select(0, rows) + within.div(across_row, rounding_mode="floor")) * tiles_x \
        + tile_x0.index_select(0, rows) + within.remainder(across_row)
    tile, slot_of = torch.sort(tile, stable=True)
    offsets = torch.zeros(tiles_x * tiles_y + 1, dtype=torch.long, device=device)
    offsets[1:] = torch.bincount(tile, minlength=tiles_x * tiles_y).cumsum(0)
    return offsets, rows.index_select(0, slot_of).int(), slot_of, first_slot, n_slots


def forward(means2d, conics, opacities, features, boxes, height: int, width: int):
    """The forward kernel (:class:`~nerf_lightning.splats.rasterize_core.TileKernels`): CUDA tensors (CPU ones in
    Triton's interpreter) -> shaded (H, W, 4), accumulation (H, W), and what :func:`backward` needs."""
    composite, _, _ = kernels(features.device.type)
    tiles_x, tiles_y = -(-width // TILE), -(-height // TILE)
    order = torch.sort(features[:, -1], stable=True).indices  # nearest first, ties by index
    # float32, or float64 where given: a footprint from a bf16 or fp16 projection (autocast's matrix products) is
    # drawn in float32, and autograd gives its gradient back in its own dtype
    dtype = torch.float64 if features.dtype == torch.float64 else torch.float32
    columns = {MEANS2D_COLUMN: means2d, CONIC_COLUMN: conics, OPACITY_COLUMN: opacities[:, None],
               FADE_COLUMN: features.new_zeros(len(features), 1), FEATURE_COLUMN: features, BOX_COLUMN: boxes,
               BOX_COLUMN + 4: features.new_zeros(len(features), PACKED - BOX_COLUMN - 4)}  # the fade limit: unread
    packed = torch.cat([columns[column].to(dtype) for column in sorted(columns)], dim=-1).index_select(0, order)
    packed = packed.contiguous()
    offsets, entries, slot_of, first_slot, n_slots = bin_footprints(packed, tiles_x, tiles_y)
    n_pixels = height * width
    shaded = packed.new_empty(n_pixels, FEATURES)
    accumulation = packed.new_empty(n_pixels)
    transmittance = torch.empty(n_pixels, dtype=torch.float64, device=features.device)
    stop = torch.empty(n_pixels, dtype=torch.long, device=features.device)
    if len(entries) == 0:  # nothing drawn (and no kernel handed an empty tensor's null pointer)
        shaded.zero_()
        accumulation.zero_()
        transmittance.fill_(1.0)
        stop.zero_()
    else:
        composite[(tiles_x * tiles_y,)](packed, offsets, entries, height, width, tiles_x, shaded, accumulation,
                                        transmittance, stop, TILE=TILE, PACKED=PACKED, MAX_ALPHA=MAX_ALPHA,
                                        MIN_ALPHA=MIN_ALPHA, MIN_TRANSMITTANCE=MIN_TRANSMITTANCE, num_warps=8)
    saved = (order, packed, offsets, entries, slot_of, first_slot, n_slots, transmittance, stop, height, width, tiles_x, tiles_y)
    return shaded.reshape(height, width, FEATURES), accumulation.reshape(height, width), saved


def backward(saved, grad_shaded: torch.Tensor, grad_accumulation: torch.Tensor) -> torch.Tensor:
    """The backward kernel: the loss's gradients of :func:`forward`'s outputs -> (M, GRADIENTS) in the footprints'
    order, in the dtype they were drawn in."""
    order, packed, offsets, entries, slot_of, first_slot, n_slots, transmittance, stop, height, width, tiles_x, tiles_y = saved
    _, composite_backward, sum_slots = kernels(packed.device.type)
    dtype = packed.dtype
    grad_shaded = grad_shaded.to(dtype).reshape(-1, FEATURES).contiguous()
    grad_accumulation = grad_accumulation.to(dtype).reshape(-1).contiguous()
    n_footprints = len(order)
    if len(entries) == 0:
        return packed.new_zeros(n_footprints, GRADIENTS)
    slot_grads = packed.new_zeros(len(entries), GRADIENTS)
    composite_backward[(tiles_x * tiles_y,)](packed, offsets, entries, slot_of, height, width, tiles_x,
                                             transmittance, stop, grad_shaded, grad_accumulation, slot_grads,
                                             TILE=TILE, PACKED=PACKED, GRADIENTS=GRADIENTS, MAX_ALPHA=MAX_ALPHA,
                                             MIN_ALPHA=MIN_ALPHA, num_warps=8)
    drawn_order = packed.new_empty(n_footprints, GRADIENTS)
    sum_slots[(triton.cdiv(n_footprints, SUM_BLOCK),)](slot_grads, first_slot, n_slots, drawn_order, n_footprints,
                                                       BLOCK=SUM_BLOCK, GRADIENTS=GRADIENTS)
    return torch.empty_like(drawn_order).index_copy_(0, order, drawn_order)  # back to the footprints' order


TRITON_TILES = TileKernels("Triton tile", forward, backward)


def rasterize_triton(projection: Projection, colours: torch.Tensor, height: int, width: int,
                     background: torch.Tensor, absgrad: bool = False) -> dict[str, torch.Tensor]:
    """Footprints (M of them) with (M, 3) colours -> rgb (H, W, 3), depth (H, W) (camera z, the weights' mean where
    something is drawn), accumulation (H, W); ``background`` (3,). CUDA tensors (CPU ones in Triton's interpreter);
    differentiable in the footprints and colours (and the background); with ``absgrad``, the backward pass fills
    ``projection.means2d.absgrad`` (:func:`~nerf_lightning.splats.rasterize_core.keep_absgrad`)."""
    return composite_features(TRITON_TILES, projection, colours, height, width, background, absgrad)
