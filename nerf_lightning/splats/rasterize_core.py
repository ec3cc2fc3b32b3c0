"""What every rasteriser shares: the footprints' pixel boxes, the absolute screen-space gradients a strategy may ask
for, the last step from weighted sums to a view, and for the two tile rasterisers (numba's
:mod:`~nerf_lightning.splats.rasterize_tiles`, Triton's :mod:`~nerf_lightning.splats.rasterize_triton`) the layout of
a packed footprint's row and of its gradient's row, named here once, and the one autograd function both run through
(:class:`TileComposite`: the forward and the backward each call one kernel of theirs).

Plain PyTorch, no fast path: the reference (:mod:`~nerf_lightning.splats.rasterize_reference`), the pairs rasteriser
(:mod:`~nerf_lightning.splats.rasterize_pairs`) and the tile kernels import it, it imports none of them.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any, NamedTuple

import torch

from nerf_lightning.splats.projection import Projection

# a tile's side in pixels (3DGS's and gsplat's 16; a Triton program's 256 lanes)
TILE = 16
# what the tile kernels draw a footprint with: its colour (3) and its depth, the last, by which they are ordered
FEATURES = 4

# A packed footprint's row, as both tile kernels read it (16 numbers: two float64 cache lines, whole float32 sectors):
MEANS2D_COLUMN = 0  # the centre (u, v)
CONIC_COLUMN = 2  # (a, b, c)
OPACITY_COLUMN = 5
FADE_COLUMN = 6  # a sigma past which the footprint is surely under 1/255 (numba's; Triton's kernels leave it unread)
FEATURE_COLUMN = 7  # FEATURES of them: colour and depth
BOX_COLUMN = 11  # the pixel box: first and last column, first and last row (:func:`pixel_boxes`)
PACKED = 16  # the row's length, one unused at the end

# A footprint's gradient, a row as the kernels write it (from one tile, then summed over its tiles):
GRAD_MEANS2D = 0  # d means2d (2)
GRAD_CONIC = 2  # d conic (3)
GRAD_OPACITY = 5  # d opacity
GRAD_FEATURES = 6  # d features (FEATURES)
GRAD_ABSOLUTE = 10  # the sums of the absolute values of each pixel's d means2d (2): its absgrad
GRADIENTS = 12  # the row's length


def pixel_boxes(projection: Projection, height: int, width: int) -> torch.Tensor:
    """(M, 4) long first and last column, first and last row of the pixels whose centres lie in each footprint's box
    (a last before a first: none)."""
    means2d, extents = projection.means2d.detach(), projection.extents.detach()
    low = torch.ceil(means2d - extents - 0.5).long()
    high = torch.floor(means2d + extents - 0.5).long()
    first = torch.stack([low[:, 0].clamp(0, width), low[:, 1].clamp(0, height)], dim=-1)
    last = torch.stack([high[:, 0].clamp(-1, width - 1), high[:, 1].clamp(-1, height - 1)], dim=-1)
    return torch.stack([first[:, 0], last[:, 0], first[:, 1], last[:, 1]], dim=-1)


def keep_absgrad(means2d: torch.Tensor, wanted: bool = True) -> torch.Tensor | None:
    """Zeros (M, 2), kept as ``means2d.absgrad`` for the backward pass to fill with each footprint's absolute
    screen-space gradient: the sum over its pixels of |d loss / d sigma_p x d sigma_p / d means2d|, each pixel's pull
    taken alone, so that opposite pulls do not cancel (AbsGS; gsplat's ``absgrad``; a strategy may read it). None,
    and nothing kept, where not ``wanted`` or where no gradient will reach ``means2d`` (M, 2)."""
    if not (wanted and torch.is_grad_enabled() and means2d.requires_grad):
        return None
    means2d.absgrad = torch.zeros(means2d.shape, dtype=torch.promote_types(means2d.dtype, torch.float32), device=means2d.device)
    return means2d.absgrad


def shaded_view(shaded: torch.Tensor, accumulation: torch.Tensor, background: torch.Tensor) -> dict[str, torch.Tensor]:
    """A view from its pixels' weighted sums of colour and depth, shaded (H, W, 4), and accumulation (H, W): rgb
    (H, W, 3) over ``background`` (3,) by what transmittance is left, depth (H, W) the weights' mean where something
    is drawn, and the accumulation. The last step of every rasteriser."""
    rgb = shaded[..., :3] + (1.0 - accumulation)[..., None] * background
    depth = shaded[..., 3] / accumulation.clamp(min=1e-10)
    return {"rgb": rgb, "depth": depth, "accumulation": accumulation}


class TileKernels(NamedTuple):
    """A tile rasteriser's two kernels, as :class:`TileComposite` calls them.

    ``forward(means2d (M, 2), conics (M, 3), opacities (M,), features (M, FEATURES), boxes (M, 4), height, width)``
    -> shaded (H, W, FEATURES) the weighted sums of the features, accumulation (H, W), and what the backward needs;
    ``backward(saved, grad_shaded (H, W, FEATURES), grad_accumulation (H, W))`` -> (M, :data:`GRADIENTS`) each
    footprint's gradient row, in the footprints' order."""

    name: str
    forward: Callable[..., tuple[torch.Tensor, torch.Tensor, Any]]
    backward: Callable[..., torch.Tensor]


class TileComposite(torch.autograd.Function):
    """(M, 2) means2d, (M, 3) conics, (M,) opacities, (M, 4) features -> (H, W, 4) weighted feature sums and (H, W)
    accumulation, differentiable in the four inputs, drawn by ``kernels`` (:class:`TileKernels`). The last feature is
    the depth the footprints are ordered by; ``boxes`` (M, 4) are their pixel boxes; ``absgrad`` (M, 2) or None, what
    the backward pass fills with the absolute screen-space gradients (:func:`keep_absgrad`)."""

    @staticmethod
    def forward(ctx, kernels: TileKernels, means2d, conics, opacities, features, boxes, height: int, width: int,
                absgrad=None):
        if features.ndim != 2 or features.shape[1] != FEATURES:
            raise ValueError(f"the {kernels.name} rasteriser draws (M, {FEATURES}) features (colour and depth), got "
                             f"{tuple(features.shape)}")
        shaded, accumulation, ctx.saved = kernels.forward(means2d, conics, opacities, features, boxes, height, width)
        ctx.kernels, ctx.absgrad, ctx.size = kernels, absgrad, (height, width)
        ctx.like = features.new_empty(0)  # the dtype and device of gradients not given
        return shaded, accumulation

    @staticmethod
    def backward(ctx, grad_shaded, grad_accumulation):
        height, width = ctx.size
        if grad_shaded is None:
            grad_shaded = ctx.like.new_zeros(height, width, FEATURES)
        if grad_accumulation is None:
            grad_accumulation = ctx.like.new_zeros(height, width)
        grads = ctx.kernels.backward(ctx.saved, grad_shaded, grad_accumulation)
        if ctx.absgrad is not None:
            # added, as the gradients are, should the graph be walked again
            ctx.absgrad.add_(grads[:, GRAD_ABSOLUTE:GRAD_ABSOLUTE + 2].to(ctx.absgrad.dtype))
        return (None, grads[:, GRAD_MEANS2D:GRAD_MEANS2D + 2], grads[:, GRAD_CONIC:GRAD_CONIC + 3], grads[:, GRAD_OPACITY],
                grads[:, GRAD_FEATURES:GRAD_FEATURES + FEATURES], None, None, None, None)


def composite_features(kernels: TileKernels, projection: Projection, colours: torch.Tensor, height: int, width: int,
                       background: torch.Tensor, absgrad: bool = False,
                       boxes: Callable[[Projection, int, int], torch.Tensor] = pixel_boxes) -> dict[str, torch.Tensor]:
    """Footprints (M of them) with (M, 3) colours -> rgb (H, W, 3), depth (H, W), accumulation (H, W) over
    ``background`` (3,), drawn by a tile rasteriser's ``kernels`` through :class:`TileComposite`: the footprints'
    features are their colours and their depth (the last, which orders them); then :func:`shaded_view`. With
    ``absgrad``, ``projection.means2d.absgrad`` is kept (:func:`keep_absgrad`). ``boxes`` is what gives the pixel
    boxes, :func:`pixel_boxes` or a fast path's equal of it."""
    features = torch.cat([colours, projection.depths[:, None].to(colours.dtype)], dim=-1)  # (M, 4): rgb, z (sorted by)
    shaded, accumulation = TileComposite.apply(kernels, projection.means2d, projection.conics, projection.opacities,
                                               features, boxes(projection, height, width), height, width,
                                               keep_absgrad(projection.means2d, absgrad))
    return shaded_view(shaded, accumulation, background)
