"""The rasteriser's CPU fast path: footprints binned into tiles and composited by numba loops, forward and backward,
as 3D Gaussian splatting and gsplat do it on a GPU.

The same values and gradients as :func:`~nerf_lightning.splats.rasterize_reference.rasterize_reference` (the tests hold
them equal), without a tensor of (footprint, pixel) pairs:

1. **Binning** (:func:`bin_footprints`): each footprint's pixel box (:func:`pixel_boxes`) says which ``tile`` x
   ``tile`` tiles it touches. The footprints are sorted nearest first once (a stable radix
   sort, ties by index, as the reference's one sort of them all), packed in that order a row each
   (:func:`pack_footprints`: a tile's loop then reads forwards through memory), and listed tile by tile.
2. **Forward** (:func:`composite_tiles`), a parallel loop over tiles: a tile keeps its pixels' transmittance and sums,
   and takes its footprints nearest first, each over the pixels of its box inside the tile only. A pair is skipped
   where alpha = min(0.999, o exp(-sigma)) < 1/255 (without an exp where sigma is past log(255 o)); a pixel is done
   before the footprint that would take its transmittance to 1e-4 or below; a tile stops when all its pixels are
   done. Each pixel keeps the transmittance it ended with and the tile-list position where it stopped.
3. **Backward** (:func:`composite_tiles_backward`): each tile walks its list back to front, recovering every pixel's
   transmittance before a footprint from the one after it (T_i = T_i+1 / (1 - alpha_i)) and the weighted gradient
   sum of the footprints behind it, so that d loss / d alpha_i = T_i g_i - (sum_{j > i} w_j g_j) / (1 - alpha_i).
   A footprint's gradient within a tile is summed over the tile's pixels in a fixed order into its own slot of the
   tile list, beside the sum of the absolute values of each pixel's pull on its centre (``means2d.absgrad``);
   :func:`sum_slots` then adds a footprint's slots in a fixed order. No two threads add into one number, so the
   same input gives the same gradients bit for bit, however the threads are scheduled.

Transmittances and sums are carried in float64 inside the loops (a pixel may take hundreds of footprints, and the
backward pass divides by 1 - alpha), the outputs are in the inputs' dtype. The Gaussian's fall-off exp(-sigma) is a
table step and a short polynomial written into the loops (:func:`fade`, within 3e-9 of exp), the four features and a
footprint's gradient sums are held in registers, and the loops are compiled with fast-math: within the tests' 1e-5 of
the reference, a pair costs a few arithmetic operations and no call.

:data:`NUMBA_TILES` (:func:`forward`, :func:`backward`) run through the tile rasterisers' one autograd function
(:class:`~nerf_lightning.splats.rasterize_core.TileComposite`, where the packed rows' columns are named).
"""

from __future__ import annotations

import numba
import numpy as np
import torch

from nerf_lightning.splats.projection import MAX_ALPHA, MIN_ALPHA, MIN_TRANSMITTANCE, Projection
from nerf_lightning.splats.rasterize_core import (BOX_COLUMN, CONIC_COLUMN, FADE_COLUMN, FEATURE_COLUMN, FEATURES,
                                                  GRAD_ABSOLUTE, GRAD_CONIC, GRAD_FEATURES, GRAD_MEANS2D, GRAD_OPACITY,
                                                  GRADIENTS, MEANS2D_COLUMN, OPACITY_COLUMN, PACKED, TILE, TileKernels,
                                                  composite_features)

# the packed row's columns as the loops read them (numba takes module constants as compile-time ones)
U, V = MEANS2D_COLUMN, MEANS2D_COLUMN + 1
A, B, C = CONIC_COLUMN, CONIC_COLUMN + 1, CONIC_COLUMN + 2
F0, F1, F2, F3 = FEATURE_COLUMN, FEATURE_COLUMN + 1, FEATURE_COLUMN + 2, FEATURE_COLUMN + 3
G_F0, G_F1, G_F2, G_F3 = GRAD_FEATURES, GRAD_FEATURES + 1, GRAD_FEATURES + 2, GRAD_FEATURES + 3
FIRST_COLUMN, LAST_COLUMN, FIRST_ROW, LAST_ROW = BOX_COLUMN, BOX_COLUMN + 1, BOX_COLUMN + 2, BOX_COLUMN + 3


def depth_keys(depths: np.ndarray) -> tuple[np.ndarray, int]:
    """(M,) float32 or float64 depths -> (M,) uint64 keys that order as the depths do (a float's bits with the sign
    bit set for positive numbers and every bit flipped for negative ones) and how many of their bits count."""
    bits = 32 if depths.dtype == np.float32 else 64
    raw = np.ascontiguousarray(depths).view(np.uint32 if bits == 32 else np.uint64).astype(np.uint64)
    sign = np.uint64(1 << (bits - 1))
    every = np.uint64((1 << bits) - 1)
    return np.where(raw & sign, ~raw & every, raw | sign), bits


@numba.njit(cache=True)
def nearest_first(keys: np.ndarray, bits: int) -> np.ndarray:
    """(M,) int32: the footprints ordered by their :func:`depth_keys` ``keys`` (M,) uint64, nearest first, ties by
    index (a stable sort). A radix sort in passes of 11 bits: stable and linear, where a comparison sort of a view's
    tens of thousands of footprints takes several times longer than compositing them."""
    n = keys.shape[0]
    order = np.arange(n).astype(np.int32)
    scratch = np.empty(n, np.int32)
    counts = np.empty(2049, np.int64)
    for shift in range(0, bits, 11):
        counts[:] = 0
        for i in range(n):
            counts[((keys[order[i]] >> shift) & 2047) + 1] += 1
        for bucket in range(2048):
            counts[bucket + 1] += counts[bucket]
        for i in range(n):
            f = order[i]
            bucket = (keys[f] >> shift) & 2047
            scratch[counts[bucket]] = f
            counts[bucket] += 1
        order, scratch = scratch, order
    return order


@numba.njit(parallel=True, cache=True)
def pack_footprints(order, means2d, conics, opacities, features, fade_limits, boxes):
    """(M, PACKED) float64: the footprints in drawing order (``order`` (M,), nearest first), a row each as the loops
    read it (its columns named in :mod:`~nerf_lightning.splats.rasterize_core`): a tile's loop reads its footprints
    forwards through one array, and binning reads the boxes in order."""
    packed = np.empty((order.shape[0], PACKED), np.float64)
    for i in numba.prange(order.shape[0]):
        f = order[i]
        packed[i, U], packed[i, V] = means2d[f, 0], means2d[f, 1]
        packed[i, A], packed[i, B], packed[i, C] = conics[f, 0], conics[f, 1], conics[f, 2]
        packed[i, OPACITY_COLUMN], packed[i, FADE_COLUMN] = opacities[f], fade_limits[f]
        for j in range(FEATURES):
            packed[i, FEATURE_COLUMN + j] = features[f, j]
        for j in range(4):
            packed[i, BOX_COLUMN + j] = boxes[f, j]
        packed[i, PACKED - 1] = 0.0
    return packed


@numba.njit(cache=True)
def bin_footprints(packed: np.ndarray, tiles_x: int, tiles_y: int):
    """The footprints, ``packed`` in drawing order (:func:`pack_footprints`), listed tile by tile.

    Returns ``offsets`` (T + 1,) int64 (tile t's footprints are ``entries[offsets[t]:offsets[t + 1]]``), ``entries``
    (E,) int32 rows of ``packed``, and ``slot_offsets`` (M + 1,) int64 and ``slots`` (E,) int64: row i's positions in
    ``entries`` are ``slots[slot_offsets[i]:slot_offsets[i + 1]]``, in tile order.

    The rows are appended to their tiles in drawing order, so every tile's list comes out nearest first, ties by
    index, as the reference's one stable sort of them all. Tiles are :data:`TILE` pixels square, a constant, so that
    finding a footprint's tiles is a shift, not a division."""
    n = packed.shape[0]
    n_tiles = tiles_x * tiles_y
    offsets = np.zeros(n_tiles + 1, np.int64)
    slot_offsets = np.zeros(n + 1, np.int64)
    for i in range(n):
        slot_offsets[i + 1] = slot_offsets[i]
        c0, c1, r0, r1 = int(packed[i, FIRST_COLUMN]), int(packed[i, LAST_COLUMN]), int(packed[i, FIRST_ROW]), int(packed[i, LAST_ROW])
        if c1 < c0 or r1 < r0:
            continue
        slot_offsets[i + 1] += (c1 // TILE - c0 // TILE + 1) * (r1 // TILE - r0 // TILE + 1)
        for ty in range(r0 // TILE, r1 // TILE + 1):
            for tx in range(c0 // TILE, c1 // TILE + 1):
                offsets[ty * tiles_x + tx + 1] += 1
    for t in range(n_tiles):
        offsets[t + 1] += offsets[t]
    entries = np.empty(offsets[n_tiles], np.int32)
    slots = np.empty(offsets[n_tiles], np.int64)
    cursor = offsets[:n_tiles].copy()
    for i in range(n):
        c0, c1, r0, r1 = int(packed[i, FIRST_COLUMN]), int(packed[i, LAST_COLUMN]), int(packed[i, FIRST_ROW]), int(packed[i, LAST_ROW])
        if c1 < c0 or r1 < r0:
            continue
        k = slot_offsets[i]
        for ty in range(r0 // TILE, r1 // TILE + 1):
            for tx in range(c0 // TILE, c1 // TILE + 1):
                t = ty * tiles_x + tx
                entries[cursor[t]] = i
                slots[k] = cursor[t]
                cursor[t] += 1
                k += 1
    return offsets, entries, slot_offsets, slots


@numba.njit(inline="always")
def tile_rectangle(t: int, tiles_x: int, tile: int, height: int, width: int):
    """Tile t's first row and column and its ends (exclusive), the image's edges cutting the last tiles short."""
    y0, x0 = (t // tiles_x) * tile, (t % tiles_x) * tile
    return y0, x0, min(y0 + tile, height), min(x0 + tile, width)


# exp(-i / FADE_STEPS) for i = 0 .. FADE_STEPS * 8: the steps of fade's table
FADE_STEPS = 64
FADE_TABLE = np.exp(-np.arange(FADE_STEPS * 8 + 2) / FADE_STEPS)


@numba.njit(inline="always", fastmath=True)
def fade(sigma: float) -> float:
    """exp(-sigma) for 0 <= sigma < 8 (the loops ask no more: a fade limit is at most log(255) plus a hair): the
    table's exp(-i / 64) at the step below, times the degree-3 Taylor polynomial of exp(-r) for the remainder
    r < 1/64, within 3e-9 of exp. A short chain of arithmetic and one load from a table in the first-level cache,
    where a call to the library's exp, or a polynomial over the whole range, takes several times as long a pair."""
    scaled = min(sigma, 8.0) * FADE_STEPS  # exp(-8) past the table's end, not off it
    step = min(max(int(scaled), 0), FADE_STEPS * 8)  # a NaN sigma stays on the table too, and gives NaN, as exp would
    r = (scaled - step) * (1.0 / FADE_STEPS)
    return FADE_TABLE[step] * (1.0 - r * (1.0 - r * (0.5 - r * (1.0 / 6.0))))


@numba.njit(parallel=True, cache=True, error_model="numpy", fastmath=True)
def composite_tiles(offsets, entries, packed, height, width, tile, tiles_x, shaded, accumulation, transmittance, stop):
    """Composite every pixel front to back. Inputs: the binning (:func:`bin_footprints`) of the footprints
    ``packed`` (M, PACKED) in drawing order (:func:`pack_footprints`; a footprint's features, colour and
    depth, are held in registers while it is drawn). Written: ``shaded`` (H * W, 4) the
    weighted sums of the features, ``accumulation`` (H * W,) the sum of the weights, ``transmittance`` (H * W,)
    float64 what is left after the last footprint drawn, ``stop`` (H * W,) int64 the tile-list position at which
    the pixel was done (its tile's end where it never was)."""
    n_tiles = offsets.shape[0] - 1
    for t in numba.prange(n_tiles):
        y0, x0, y1, x1 = tile_rectangle(t, tiles_x, tile, height, width)
        tile_width = x1 - x0
        n_pixels = (y1 - y0) * tile_width
        left = np.ones(n_pixels, np.float64)
        sums = np.zeros((n_pixels, 5), np.float64)  # 4 features and the weight
        ends = np.full(n_pixels, offsets[t + 1], np.int64)
        active = n_pixels
        end = offsets[t + 1]
        for k in range(offsets[t], end):
            if active == 0:
                break
            r = entries[k]
            mx, my = packed[r, U], packed[r, V]
            half_a, b, half_c = 0.5 * packed[r, A], packed[r, B], 0.5 * packed[r, C]
            o, faint = packed[r, OPACITY_COLUMN], packed[r, FADE_COLUMN]
            f0, f1, f2, f3 = packed[r, F0], packed[r, F1], packed[r, F2], packed[r, F3]
            first, last = max(int(packed[r, FIRST_COLUMN]), x0), min(int(packed[r, LAST_COLUMN]), x1 - 1)
            for row in range(max(int(packed[r, FIRST_ROW]), y0), min(int(packed[r, LAST_ROW]), y1 - 1) + 1):
                dy = row + 0.5 - my
                b_dy, c_dy2 = b * dy, half_c * dy * dy
                base = (row - y0) * tile_width - x0
                for column in range(first, last + 1):
                    p = base + column
                    if ends[p] != end:
                        continue
                    dx = column + 0.5 - mx
                    sigma = (half_a * dx + b_dy) * dx + c_dy2
                    if sigma < 0.0 or sigma > faint:  # faint: alpha surely under 1/255, no exp needed
                        continue
                    alpha = min(MAX_ALPHA, o * fade(sigma))
                    if alpha < MIN_ALPHA:
                        continue
                    before = left[p]
                    after = before * (1.0 - alpha)
                    if after <= MIN_TRANSMITTANCE:
                        ends[p] = k
                        active -= 1
                        continue
                    weight = alpha * before
                    sums[p, 0] += weight * f0
                    sums[p, 1] += weight * f1
                    sums[p, 2] += weight * f2
                    sums[p, 3] += weight * f3
                    sums[p, 4] += weight
                    left[p] = after
        for p in range(n_pixels):
            pixel = (y0 + p // tile_width) * width + x0 + p % tile_width
            for i in range(4):
                shaded[pixel, i] = sums[p, i]
            accumulation[pixel] = sums[p, 4]
            transmittance[pixel] = left[p]
            stop[pixel] = ends[p]


@numba.njit(parallel=True, cache=True, error_model="numpy", fastmath=True)
def composite_tiles_backward(offsets, entries, packed, height, width, tile, tiles_x, transmittance, stop, grad_shaded,
                             grad_accumulation, slot_grads):
    """The gradients of :func:`composite_tiles`, back to front. ``grad_shaded`` (H * W, 4) and ``grad_accumulation``
    (H * W,) are the loss's gradients of its outputs; written: ``slot_grads`` (E, GRADIENTS), for each
    tile-list entry its footprint's gradient from that tile's pixels: d means2d (2), d conics (3), d opacity, d
    features (4), and the sums of the absolute values of each pixel's d means2d (2)."""
    n_tiles = offsets.shape[0] - 1
    for t in numba.prange(n_tiles):
        y0, x0, y1, x1 = tile_rectangle(t, tiles_x, tile, height, width)
        tile_width = x1 - x0
        n_pixels = (y1 - y0) * tile_width
        left = np.empty(n_pixels, np.float64)
        behind = np.zeros(n_pixels, np.float64)  # sum over the footprints behind of w_j g_j
        ends = np.empty(n_pixels, np.int64)
        grad_in = np.empty((n_pixels, 5), np.float64)  # the pixel's gradients of its 4 sums and its accumulation
        for p in range(n_pixels):
            pixel = (y0 + p // tile_width) * width + x0 + p % tile_width
            left[p], ends[p] = transmittance[pixel], stop[pixel]
            for i in range(4):
                grad_in[p, i] = grad_shaded[pixel, i]
            grad_in[p, 4] = grad_accumulation[pixel]
        for k in range(offsets[t + 1] - 1, offsets[t] - 1, -1):
            r = entries[k]
            mx, my = packed[r, U], packed[r, V]
            a, b, c = packed[r, A], packed[r, B], packed[r, C]
            o, faint = packed[r, OPACITY_COLUMN], packed[r, FADE_COLUMN]
            f0, f1, f2, f3 = packed[r, F0], packed[r, F1], packed[r, F2], packed[r, F3]
            first, last = max(int(packed[r, FIRST_COLUMN]), x0), min(int(packed[r, LAST_COLUMN]), x1 - 1)
            g_mx = g_my = g_a = g_b = g_c = g_o = g_f0 = g_f1 = g_f2 = g_f3 = g_ax = g_ay = 0.0
            for row in range(max(int(packed[r, FIRST_ROW]), y0), min(int(packed[r, LAST_ROW]), y1 - 1) + 1):
                dy = row + 0.5 - my
                b_dy, c_dy2 = b * dy, 0.5 * c * dy * dy
                base = (row - y0) * tile_width - x0
                for column in range(first, last + 1):
                    p = base + column
                    if k >= ends[p]:
                        continue
                    dx = column + 0.5 - mx
                    sigma = (0.5 * a * dx + b_dy) * dx + c_dy2
                    if sigma < 0.0 or sigma > faint:
                        continue
                    falloff = fade(sigma)
                    alpha = min(MAX_ALPHA, o * falloff)
                    if alpha < MIN_ALPHA:
                        continue
                    keep = 1.0 / (1.0 - alpha)
                    before = left[p] * keep
                    weight = alpha * before
                    s0, s1, s2, s3 = grad_in[p, 0], grad_in[p, 1], grad_in[p, 2], grad_in[p, 3]
                    grad_weight = grad_in[p, 4] + s0 * f0 + s1 * f1 + s2 * f2 + s3 * f3
                    g_f0 += weight * s0
                    g_f1 += weight * s1
                    g_f2 += weight * s2
                    g_f3 += weight * s3
                    grad_alpha = before * grad_weight - behind[p] * keep
                    behind[p] += weight * grad_weight
                    left[p] = before
                    if o * falloff <= MAX_ALPHA:  # the clamp passes no gradient
                        g_o += falloff * grad_alpha
                        grad_sigma = -alpha * grad_alpha
                        pull_x, pull_y = grad_sigma * (a * dx + b * dy), grad_sigma * (c * dy + b * dx)
                        g_mx -= pull_x
                        g_my -= pull_y
                        g_ax += abs(pull_x)
                        g_ay += abs(pull_y)
                        g_a += grad_sigma * 0.5 * dx * dx
                        g_b += grad_sigma * dx * dy
                        g_c += grad_sigma * 0.5 * dy * dy
            slot_grads[k, GRAD_MEANS2D], slot_grads[k, GRAD_MEANS2D + 1], slot_grads[k, GRAD_OPACITY] = g_mx, g_my, g_o
            slot_grads[k, GRAD_CONIC], slot_grads[k, GRAD_CONIC + 1], slot_grads[k, GRAD_CONIC + 2] = g_a, g_b, g_c
            slot_grads[k, G_F0], slot_grads[k, G_F1], slot_grads[k, G_F2], slot_grads[k, G_F3] = g_f0, g_f1, g_f2, g_f3
            slot_grads[k, GRAD_ABSOLUTE], slot_grads[k, GRAD_ABSOLUTE + 1] = g_ax, g_ay


@numba.njit(parallel=True, cache=True, error_model="numpy")
def sum_slots(order, slot_offsets, slots, slot_grads, out):
    """``out`` (M, G): each footprint's gradient, the sum of its tile-list slots (``slot_grads`` (E, G)) in tile
    order; the slots are listed by drawing order, footprint ``order[i]``'s at ``slot_offsets[i]``."""
    for i in numba.prange(order.shape[0]):
        f = order[i]
        for j in range(slot_offsets[i], slot_offsets[i + 1]):
            for g in range(out.shape[1]):
                out[f, g] += slot_grads[slots[j], g]


def fade_limits(opacities: np.ndarray) -> np.ndarray:
    """(M,) float64 for (M,) opacities: a sigma past which o exp(-sigma) is surely under 1/255 (log(255 o), plus a
    margin for rounding), so that the loops skip those pixels without an exp; the exact alpha test follows for the rest."""
    # opacities are at most 1 (a limit of log(255)); the cap keeps any other input on fade's table
    return np.minimum(np.log(np.maximum(opacities.astype(np.float64) / MIN_ALPHA, 1.0)) + 1e-6, 7.9)


def _numpy(tensor: torch.Tensor) -> np.ndarray:
    return tensor.detach().contiguous().numpy()


@numba.njit(cache=True)
def pixel_boxes_loop(means2d, extents, half, height, width, boxes):
    """:func:`~nerf_lightning.splats.rasterize_core.pixel_boxes` of (M, 2) means2d and extents into ``boxes`` (M, 4)
    int64, in the inputs' precision as PyTorch computes it (``half``: a one-element array of 0.5 in their dtype)."""
    for i in range(means2d.shape[0]):
        for axis, size in ((0, width), (1, height)):
            low = np.ceil(means2d[i, axis] - extents[i, axis] - half[0])
            high = np.floor(means2d[i, axis] + extents[i, axis] - half[0])
            boxes[i, 2 * axis] = min(max(int(low), 0), size)
            boxes[i, 2 * axis + 1] = min(max(int(high), -1), size - 1)


def pixel_boxes(projection: Projection, height: int, width: int) -> torch.Tensor:
    """:func:`~nerf_lightning.splats.rasterize_core.pixel_boxes` in one numba loop (seventeen tensor operators there)."""
    means2d, extents = _numpy(projection.means2d), _numpy(projection.extents)
    boxes = torch.empty((len(means2d), 4), dtype=torch.int64)
    pixel_boxes_loop(means2d, extents, np.full(1, 0.5, means2d.dtype), height, width, boxes.numpy())
    return boxes


def forward(means2d, conics, opacities, features, boxes, height: int, width: int):
    """The forward kernel (:class:`~nerf_lightning.splats.rasterize_core.TileKernels`): CPU tensors -> shaded (H, W, 4),
    accumulation (H, W) in the features' dtype, and what :func:`backward` needs."""
    tiles_x, tiles_y = -(-width // TILE), -(-height // TILE)
    means2d_array, conics_array, opacities_array, features_array = (_numpy(x) for x in (means2d, conics, opacities, features))
    order = nearest_first(*depth_keys(features_array[:, -1]))
    packed = pack_footprints(order, means2d_array, conics_array, opacities_array, features_array,
                             fade_limits(opacities_array), _numpy(boxes))
    offsets, entries, slot_offsets, slots = bin_footprints(packed, tiles_x, tiles_y)
    n_pixels, dtype = height * width, features_array.dtype
    shaded = np.empty((n_pixels, FEATURES), dtype)
    accumulation = np.empty(n_pixels, dtype)
    transmittance = np.empty(n_pixels, np.float64)
    stop = np.empty(n_pixels, np.int64)
    composite_tiles(offsets, entries, packed, height, width, TILE, tiles_x, shaded, accumulation, transmittance, stop)
    saved = (order, offsets, entries, slot_offsets, slots, packed, dtype, transmittance, stop, height, width, tiles_x)
    return torch.from_numpy(shaded).reshape(height, width, -1), torch.from_numpy(accumulation).reshape(height, width), saved


def backward(saved, grad_shaded: torch.Tensor, grad_accumulation: torch.Tensor) -> torch.Tensor:
    """The backward kernel: the loss's gradients of :func:`forward`'s outputs -> (M, GRADIENTS) in the footprints'
    order, in their dtype."""
    order, offsets, entries, slot_offsets, slots, packed, dtype, transmittance, stop, height, width, tiles_x = saved
    grad_shaded = _numpy(grad_shaded).astype(dtype, copy=False).reshape(-1, FEATURES)
    grad_accumulation = _numpy(grad_accumulation).astype(dtype, copy=False).reshape(-1)
    slot_grads = np.empty((len(entries), GRADIENTS), np.float64)
    composite_tiles_backward(offsets, entries, packed, height, width, TILE, tiles_x, transmittance, stop,
                             grad_shaded, grad_accumulation, slot_grads)
    grads = np.zeros((len(order), GRADIENTS), np.float64)
    sum_slots(order, slot_offsets, slots, slot_grads, grads)
    return torch.from_numpy(grads.astype(dtype))


NUMBA_TILES = TileKernels("numba tile", forward, backward)


def rasterize_tiles(projection: Projection, colours: torch.Tensor, height: int, width: int,
                    background: torch.Tensor, absgrad: bool = False) -> dict[str, torch.Tensor]:
    """Footprints (M of them) with (M, 3) colours -> rgb (H, W, 3), depth (H, W) (camera z, the weights' mean where
    something is drawn), accumulation (H, W); ``background`` (3,). CPU tensors; differentiable in the footprints and
    colours (and the background); with ``absgrad``, the backward pass fills ``projection.means2d.absgrad``
    (:func:`~nerf_lightning.splats.rasterize_core.keep_absgrad`)."""
    return composite_features(NUMBA_TILES, projection, colours, height, width, background, absgrad, pixel_boxes)
