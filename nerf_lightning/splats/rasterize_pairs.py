"""The pairs rasteriser: footprints to pixels through (footprint, pixel) pairs, in plain PyTorch on every device.

The same values as :func:`~nerf_lightning.splats.rasterize_reference.rasterize_reference` (the tests hold them
equal), but only where a footprint can be drawn: each footprint lists the pixels of its box (``repeat_interleave``,
no loop over footprints), the pairs too faint are dropped, one sort orders the rest by pixel and then by depth, and
:func:`~nerf_lightning.rendering.compositing.weights_from_alpha_packed` composites each pixel's pairs front to back,
as the NeRF renderers composite a ray's samples (a pixel is a ray whose samples are footprints).

Memory grows with the pairs, about 100 bytes each with gradients: a view whose pairs exceed ``max_pairs`` is drawn in
bands of rows, each within the budget (a single row over it is drawn alone).

Asked with ``absgrad=True``, every rasteriser's backward pass also leaves ``means2d.absgrad``
(:func:`~nerf_lightning.splats.rasterize_core.keep_absgrad`): for each footprint, the sum over its pixels of the
absolute value of each pixel's pull on its centre (AbsGS's densification statistic, which a strategy asks for).
"""

from __future__ import annotations

import torch

from nerf_lightning.rendering.compositing import weights_from_alpha_packed
from nerf_lightning.splats.projection import MAX_ALPHA, MIN_ALPHA, MIN_TRANSMITTANCE, Projection
from nerf_lightning.splats.rasterize_core import keep_absgrad, pixel_boxes, shaded_view

# pairs drawn at once: about 0.4 GB with gradients (the budget a view's bands are cut to)
MAX_PAIRS = 4_000_000


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


def rasterize_pairs(projection: Projection, colours: torch.Tensor, height: int, width: int, background: torch.Tensor,
                    max_pairs: int = MAX_PAIRS, absgrad: bool = False) -> dict[str, torch.Tensor]:
    """Footprints (M of them) with (M, 3) colours -> rgb (H, W, 3), depth (H, W) (camera z, the weights' mean where
    something is drawn), accumulation (H, W); ``background`` (3,). Differentiable in the footprints and colours; with
    ``absgrad``, the backward pass fills ``projection.means2d.absgrad``
    (:func:`~nerf_lightning.splats.rasterize_core.keep_absgrad`: here about a tenth more time a step, for the pairs'
    own pulls)."""
    absgrad = keep_absgrad(projection.means2d, absgrad)
    # footprints nearest first: pairs are listed footprint by footprint, so one stable sort by pixel leaves every
    # pixel's pairs nearest first (ties by the footprints' order)
    nearest_first = torch.sort(projection.depths.detach(), stable=True).indices
    projection = Projection(*(value.index_select(0, nearest_first) for value in projection))
    shades = torch.cat([colours.index_select(0, nearest_first), projection.depths[:, None]], dim=-1)  # (M, 4): rgb, z
    boxes = pixel_boxes(projection, height, width)
    footprints = footprint_table(projection)
    n_pixels = height * width
    shaded = colours.new_zeros(n_pixels, 4)
    accumulation = colours.new_zeros(n_pixels)
    for start, stop in row_bands(boxes, height, max_pairs):
        footprint, pixel, alpha = drawn_pairs(footprints, boxes, start, stop, width,
                                              None if absgrad is None else (absgrad, nearest_first))
        pixel, order = torch.sort(pixel, stable=True)
        pixel, footprint, alpha = pixel.long(), footprint.index_select(0, order), alpha.index_select(0, order)
        # the band's pixels numbered from its first: compositing lays out rows of pairs for each of them only
        composited = weights_from_alpha_packed(alpha, pixel - start * width, (stop - start) * width)
        done = (composited.transmittance * (1.0 - alpha)).detach() <= MIN_TRANSMITTANCE
        weights = torch.where(done, torch.zeros_like(alpha), composited.weights)
        shaded = shaded.index_add(0, pixel, weights[:, None] * shades.index_select(0, footprint))
        accumulation = accumulation.index_add(0, pixel, weights)
    return shaded_view(shaded.reshape(height, width, 4), accumulation.reshape(height, width), background)


def footprint_table(projection: Projection) -> torch.Tensor:
    """(M, 6) what a pair needs of its footprint, in one row so that one gather fetches it: the centre (u, v), the
    conic (a, b, c) and the opacity."""
    return torch.cat([projection.means2d, projection.conics, projection.opacities[:, None]], dim=-1)


def drawn_pairs(footprints: torch.Tensor, boxes: torch.Tensor, start: int, stop: int, width: int,
                absgrad: tuple[torch.Tensor, torch.Tensor] | None = None) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """The (footprint, pixel) pairs drawn within rows [start, stop), footprint by footprint and each box row-major:
    (P,) int32 footprint indices, (P,) int32 pixel indices (row * W + column) and (P,) alphas,
    min(0.999, o exp(-sigma)), the pixels of each footprint's box where the alpha is at least 1/255.

    ``footprints`` (M, 6) is :func:`footprint_table`, ``boxes`` (M, 4)
    :func:`~nerf_lightning.splats.rasterize_core.pixel_boxes`. The pairs are listed in two steps, each a
    ``repeat_interleave``: every footprint's rows within its box (a span), then the columns of each span where the
    footprint is drawn. Along a span dy is fixed and sigma = 0.5 (a dx^2 + c dy^2) + b dx dy is a quadratic in dx, so
    those columns are the interval where sigma <= log(255 o), solved for once a span: no pair is listed only to be
    dropped.

    With ``absgrad`` (a (M0, 2) sum and (M,) the row of it each footprint adds to), the backward pass adds each pair's
    absolute pull on its footprint's centre, |d loss / d sigma| x |(a dx + b dy, b dx + c dy)|
    (:func:`~nerf_lightning.splats.rasterize_core.keep_absgrad`)."""
    device = boxes.device
    first_row, last_row = boxes[:, 2].clamp(min=start), boxes[:, 3].clamp(max=stop - 1)
    columns = (boxes[:, 1] - boxes[:, 0] + 1).clamp(min=0)
    rows = torch.where(columns > 0, (last_row - first_row + 1).clamp(min=0), 0)
    n_spans = int(rows.sum())
    span = torch.repeat_interleave(torch.arange(len(boxes), device=device), rows, output_size=n_spans)  # (R,) footprint
    row = first_row.index_select(0, span) + torch.arange(n_spans, device=device) - (rows.cumsum(0) - rows).index_select(0, span)
    span_boxes = boxes.index_select(0, span)
    u, v, a, b, c, opacity = footprints.index_select(0, span).unbind(-1)  # (R,) each
    dy = row.to(v.dtype) + 0.5 - v
    with torch.no_grad():  # which columns: a choice, not a value to differentiate
        # sigma <= log(o / (1/255)) <=> 0.5 a dx^2 + b dy dx + (0.5 c dy^2 - log(255 o)) <= 0
        b_dy = b * dy
        discriminant = b_dy * b_dy - a * (c * dy * dy - 2.0 * torch.log((opacity / MIN_ALPHA).clamp(min=1e-30)))
        root = torch.sqrt(discriminant.clamp(min=0.0))
        first = torch.ceil(u - 0.5 + (-b_dy - root) / a).clamp(-1, width).long().maximum(span_boxes[:, 0])
        last = torch.floor(u - 0.5 + (-b_dy + root) / a).clamp(-1, width).long().minimum(span_boxes[:, 1])
        span_columns = torch.where(discriminant >= 0, (last - first + 1).clamp(min=0), 0)
    n_pairs = int(span_columns.sum())
    which = torch.repeat_interleave(torch.arange(n_spans, device=device), span_columns, output_size=n_pairs)  # (P,) span
    step = torch.arange(n_pairs, device=device) - (span_columns.cumsum(0) - span_columns).index_select(0, which)  # along it
    dx0 = first.to(u.dtype) + 0.5 - u  # dx at the span's first drawn pixel
    spans = torch.stack([0.5 * a, dx0, b * dy, 0.5 * c * dy * dy, opacity], dim=-1)  # (R, 5)
    half_a, dx0, b_dy, half_c_dy2, opacity = spans.index_select(0, which).unbind(-1)  # (P,) each
    dx = step.to(dx0.dtype) + dx0
    sigma = (half_a * dx + b_dy) * dx + half_c_dy2
    alpha = (opacity * torch.exp(-sigma)).clamp(max=MAX_ALPHA)
    footprint = span.int().index_select(0, which)
    pixel = (row * width + first).int().index_select(0, which) + step.int()
    if absgrad is not None and sigma.requires_grad:
        total, rows = absgrad
        pair_rows = rows.index_select(0, footprint.long())

        def add_pulls(grad_sigma: torch.Tensor) -> None:  # (P,) d loss / d sigma of each pair
            with torch.no_grad():
                b_p, c_p, dy_p = (value.detach().index_select(0, which) for value in (b, c, dy))
                x = dx.detach()
                pull = torch.stack([2.0 * half_a.detach() * x + b_p * dy_p, b_p * x + c_p * dy_p], dim=-1)  # (P, 2)
                total.index_add_(0, pair_rows, (grad_sigma[:, None] * pull).abs().to(total.dtype))

        sigma.register_hook(add_pulls)
    return footprint, pixel, alpha
