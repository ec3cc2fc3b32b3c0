"""Image-quality metrics. PSNR and SSIM come from kornia; this adds PSNR from an MSE already computed."""

from __future__ import annotations

import torch


def mse_to_psnr(mse: torch.Tensor) -> torch.Tensor:
    """PSNR in dB of colours in [0, 1] from their mean squared error: -10 log10(mse)."""
    return -10.0 * torch.log10(mse)
