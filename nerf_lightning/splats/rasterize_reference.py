"""The reference rasteriser: every footprint evaluated at every pixel, composited front to back. The maths of
splatting in a screenful, for small images and for the tests that hold the fast ones equal to it (the pairs rasteriser
:mod:`~nerf_lightning.splats.rasterize_pairs`, the tile kernels :mod:`~nerf_lightning.splats.rasterize_tiles` and
:mod:`~nerf_lightning.splats.rasterize_triton`); memory grows as footprints x pixels.

At pixel centre p, footprint g (centre m_g, conic Q_g, opacity o_g) has

    sigma = 1/2 (p - m_g)^T Q_g (p - m_g),    alpha = min(0.999, o_g exp(-sigma)),

and counts only inside its box (|p - m_g| <= its extents) and where alpha >= 1/255. The footprints are taken nearest
first (camera z, ties by index) and composited with :func:`~nerf_lightning.rendering.compositing.weights_from_alpha`;
a pixel is done before the footprint that would take its transmittance to 1e-4 or below (3DGS's early stop), and
the background shows through what transmittance is left.
"""

from __future__ import annotations

import torch

from nerf_lightning.rendering.compositing import weights_from_alpha
from nerf_lightning.splats.projection import MAX_ALPHA, MIN_ALPHA, MIN_TRANSMITTANCE, Projection
from nerf_lightning.splats.rasterize_core import keep_absgrad, shaded_view


def rasterize_reference(projection: Projection, colours: torch.Tensor, height: int, width: int,
                        background: torch.Tensor, absgrad: bool = False) -> dict[str, torch.Tensor]:
    """Footprints (M of them) with (M, 3) colours -> rgb (H, W, 3), depth (H, W) (camera z, where something is
    drawn: the weights' mean), accumulation (H, W); ``background`` (3,). With ``absgrad``, the backward pass fills
    ``projection.means2d.absgrad`` (:func:`~nerf_lightning.splats.rasterize_core.keep_absgrad`)."""
    v, u = torch.meshgrid(torch.arange(height, device=colours.device, dtype=colours.dtype) + 0.5,
                          torch.arange(width, device=colours.device, dtype=colours.dtype) + 0.5, indexing="ij")
    order = torch.sort(projection.depths.detach(), stable=True).indices  # nearest first
    means2d, conics = projection.means2d[order], projection.conics[order]
    dx = u.reshape(1, -1) - means2d[:, 0:1]  # (M, H * W)
    dy = v.reshape(1, -1) - means2d[:, 1:2]
    a, b, c = conics[:, 0:1], conics[:, 1:2], conics[:, 2:3]
    sigma = 0.5 * (a * dx * dx + c * dy * dy) + b * dx * dy
    absgrad = keep_absgrad(projection.means2d, absgrad)
    if absgrad is not None:  # each pixel's pull on a footprint's centre, d loss / d sigma x d sigma / d means2d, alone
        def add_pulls(grad_sigma: torch.Tensor) -> None:  # (M, H * W)
            x, y = dx.detach(), dy.detach()
            pull = torch.stack([a.detach() * x + b.detach() * y, b.detach() * x + c.detach() * y], dim=-1)  # (M, H * W, 2)
            absgrad.index_add_(0, order, (grad_sigma[..., None] * pull).abs().sum(dim=1).to(absgrad.dtype))

        sigma.register_hook(add_pulls)
    alpha = (projection.opacities[order, None] * torch.exp(-sigma)).clamp(max=MAX_ALPHA)
    extents = projection.extents[order].detach()
    counts = (dx.detach().abs() <= extents[:, 0:1]) & (dy.detach().abs() <= extents[:, 1:2]) & (sigma.detach() >= 0) \
        & (alpha.detach() >= MIN_ALPHA)
    alpha = torch.where(counts, alpha, torch.zeros_like(alpha)).t()  # (H * W, M): a pixel's row, nearest first
    composited = weights_from_alpha(alpha)
    done = (composited.transmittance * (1.0 - alpha)).detach() <= MIN_TRANSMITTANCE
    weights = torch.where(done, torch.zeros_like(alpha), composited.weights)
    shaded = weights @ torch.cat([colours[order], projection.depths[order, None]], dim=-1)  # (H * W, 4): rgb, z
    return shaded_view(shaded.reshape(height, width, 4), weights.sum(dim=-1).reshape(height, width), background)
