"""The splats' photometric loss, the reference: (1 - w) L1 + w (1 - SSIM) of a drawn view against its photo (3DGS's),
in PyTorch over :func:`~nerf_lightning.metrics.ssim_map`. :mod:`~nerf_lightning.splats.loss_fast` gives the same
value and gradient in one numba pass on a CPU; the tests hold the two equal."""

from __future__ import annotations

import torch

from nerf_lightning.metrics import ssim_map


def photometric_loss(rgb: torch.Tensor, image: torch.Tensor, ssim_weight: float,
                     mask: torch.Tensor | None = None) -> torch.Tensor:
    """() (1 - ssim_weight) L1 + ssim_weight (1 - SSIM) of rgb (H, W, 3) against image (H, W, 3): means over the
    pixels, or over ``mask`` (H, W) bool where given. SSIM is kornia's (11x11 Gaussian window, reflect padding)."""
    similarity = ssim_map(rgb.permute(2, 0, 1)[None], image.permute(2, 0, 1)[None])
    if mask is None:
        l1, ssim = (rgb - image).abs().mean(), similarity.mean()
    else:
        count = mask.sum().clamp(min=1)
        l1 = ((rgb - image).abs().mean(dim=-1) * mask).sum() / count
        ssim = (similarity[0].mean(dim=0) * mask).sum() / count
    return (1.0 - ssim_weight) * l1 + ssim_weight * (1.0 - ssim)
