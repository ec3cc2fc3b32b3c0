"""The rasteriser: footprints to pixels through (footprint, pixel) pairs, in plain PyTorch on every device.

The same values as :func:`~nerf_lightning.splats.rasterize_dense.rasterize_dense` (the tests hold them equal), but
only where a footprint can be drawn: each footprint lists the pixels of its box (``repeat_interleave``, no loop over
footprints), the pairs too faint are dropped, one sort orders the rest by pixel and then by depth, and
:func:`~nerf_lightning.rendering.compositing.weights_from_alpha_packed` composites each pixel's pairs front to back,
as the NeRF renderers composite a ray's samples (a pixel is a ray whose samples are footprints).

Memory grows with the pairs, about 100 bytes each with gradients: a view whose pairs exceed ``max_pairs`` is drawn in
bands of rows, each within the budget (a single row over it is drawn alone).
"""

from __future__ import annotations

import torch

from nerf_lightning.rendering.compositing import weights_from_alpha_packed
from nerf_lightning.splats.projection import MIN_ALPHA, Projection
from nerf_lightning.splats.rasterize_dense import MAX_ALPHA, MIN_TRANSMITTANCE

# pairs drawn at once: about 0.4 GB with gradients (the budget a view's bands are cut to)
MAX_PAIRS = 4_000_000


def pixel_boxes(projection: Projection, height: int, width: int) -> torch.Tensor:
    """(M, 4) long first and last column, first and last row of the pixels whose centres lie in each footprint's box
    (a last before a first: none)."""
    means2d, extents = projection.means2d.detach(), projection.extents.detach()
    low = torch.ceil(means2d - extents - 0.5).long()
    high = torch.floor(means2d + extents - 0.5).long()
    first = torch.stack([low[:, 0].clamp(0, width), low[:, 1].clamp(0, height)], dim=-1)
    last = torch.stack([high[:, 0].clamp(-1, width - 1), high[:, 1].clamp(-1, height - 1)], dim=-1)
    return torch.stack([first[:, 0], last[:, 0], first[:, 1], last[:, 1]], dim=-1)


def row_bands(boxes: torch.Tensor, height: int, max_pairs: int) -> list[tuple[int, int]]:
    """Rows [start, stop) cut so that each band's pairs stay within ``max_pairs`` (a row over it alone): the pairs of
    each row counted with a difference array over the boxes' rows."""
    columns = (boxes[:, 1] - boxes[:, 0] + 1).clamp(min=0)
    has_rows = boxes[:, 3] >= boxes[:, 2]
    per_row = torch.zeros(height + 1, dtype=torch.long, device=boxes.device)
    per_row.index_add_(0, boxes[has_rows, 2], columns[has_rows])
    per_row.index_add_(0, boxes[has_rows, 3] + 1, -columns[has_rows])
    per_row = per_row.cumsum(0)[:height].tolist()
    bands, start, total = [], 0, 0
    for row, pairs in enumerate(per_row):
        if total + pairs > max_pairs and row > start:
            bands.append((start, row))
            start, total = row, 0
        total += pairs
    bands.append((start, height))
    return bands


def rasterize(projection: Projection, colours: torch.Tensor, height: int, width: int, background: torch.Tensor,
              max_pairs: int = MAX_PAIRS) -> dict[str, torch.Tensor]:
    """Footprints (M of them) with (M, 3) colours -> rgb (H, W, 3), depth (H, W) (camera z, the weights' mean where
    something is drawn), accumulation (H, W); ``background`` (3,). Differentiable in the footprints and colours."""
    n_pixels = height * width
    rgb = colours.new_zeros(n_pixels, 3)
    depth_sum = colours.new_zeros(n_pixels)
    accumulation = colours.new_zeros(n_pixels)
    boxes = pixel_boxes(projection, height, width)
    # a footprint's place in depth order (ties by index): the second sort key
    rank = torch.empty_like(projection.depths, dtype=torch.long)
    rank[torch.sort(projection.depths.detach(), stable=True).indices] = torch.arange(len(rank), device=rank.device)
    for start, stop in row_bands(boxes, height, max_pairs):
        footprint, pixel = _pairs(boxes, start, stop, width)
        alpha, pixel, footprint = _drawn(projection, footprint, pixel, width)
        order = torch.sort(pixel * max(len(rank), 1) + rank[footprint]).indices  # by pixel, then nearest first
        alpha, pixel, footprint = alpha[order], pixel[order], footprint[order]
        # the band's pixels numbered from its first: compositing lays out a row of pairs for each of them only
        composited = weights_from_alpha_packed(alpha, pixel - start * width, (stop - start) * width)
        done = (composited.transmittance * (1.0 - alpha)).detach() <= MIN_TRANSMITTANCE
        weights = torch.where(done, torch.zeros_like(alpha), composited.weights)
        rgb = rgb.index_add(0, pixel, weights[:, None] * colours[footprint])
        depth_sum = depth_sum.index_add(0, pixel, weights * projection.depths[footprint])
        accumulation = accumulation.index_add(0, pixel, weights)
    rgb = rgb + (1.0 - accumulation)[:, None] * background
    depth = depth_sum / accumulation.clamp(min=1e-10)
    return {"rgb": rgb.reshape(height, width, 3), "depth": depth.reshape(height, width),
            "accumulation": accumulation.reshape(height, width)}


def _pairs(boxes: torch.Tensor, start: int, stop: int, width: int) -> tuple[torch.Tensor, torch.Tensor]:
    """Every (footprint, pixel) of the boxes within rows [start, stop): (P,) footprint indices and (P,) pixel indices
    (row * W + column), footprint by footprint, each box row-major."""
    first_row, last_row = boxes[:, 2].clamp(min=start), boxes[:, 3].clamp(max=stop - 1)
    columns = (boxes[:, 1] - boxes[:, 0] + 1).clamp(min=0)
    counts = columns * (last_row - first_row + 1).clamp(min=0)
    footprint = torch.repeat_interleave(torch.arange(len(boxes), device=boxes.device), counts)
    within = torch.arange(len(footprint), device=boxes.device) - (counts.cumsum(0) - counts)[footprint]
    row = first_row[footprint] + within // columns[footprint].clamp(min=1)
    column = boxes[footprint, 0] + within % columns[footprint].clamp(min=1)
    return footprint, row * width + column


def _drawn(projection: Projection, footprint: torch.Tensor, pixel: torch.Tensor,
           width: int) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """The pairs' alphas, min(0.999, o exp(-sigma)), and the pairs kept: those at least 1/255 (with sigma >= 0)."""
    centres = torch.stack([pixel % width, pixel // width], dim=-1).to(projection.means2d.dtype) + 0.5
    d = centres - projection.means2d[footprint]  # (P, 2)
    conics = projection.conics[footprint]
    sigma = 0.5 * (conics[:, 0] * d[:, 0] * d[:, 0] + conics[:, 2] * d[:, 1] * d[:, 1]) + conics[:, 1] * d[:, 0] * d[:, 1]
    alpha = (projection.opacities[footprint] * torch.exp(-sigma)).clamp(max=MAX_ALPHA)
    keep = torch.nonzero((sigma.detach() >= 0) & (alpha.detach() >= MIN_ALPHA)).squeeze(1)
    return alpha[keep], pixel[keep], footprint[keep]
