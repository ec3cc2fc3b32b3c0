"""Input encodings that lift low-dimensional coordinates to features an MLP can fit detail with."""

from __future__ import annotations

import math

import torch
from torch import nn


class SinusoidalEncoding(nn.Module):
    """NeRF's positional encoding with the raw input kept.

    ``PE(x) = [x, sin(2^0 pi x), cos(2^0 pi x), ..., sin(2^(L-1) pi x), cos(2^(L-1) pi x)]``

    Layout of the output's last axis: the ``in_dim`` raw values, then for each level ``k = 0..L-1`` the
    ``in_dim`` sines followed by the ``in_dim`` cosines of ``2^k pi x``. Its width is ``in_dim * (1 + 2L)``,
    for example ``2 + 4L`` for image coordinates.

    Args:
        in_dim: number of coordinates D.
        num_frequencies: number of frequency levels L (0 keeps only the raw input).
        include_input: keep the raw coordinates at the front.
    """

    def __init__(self, in_dim: int, num_frequencies: int, include_input: bool = True) -> None:
        super().__init__()
        if in_dim < 1 or num_frequencies < 0:
            raise ValueError(f"SinusoidalEncoding needs in_dim >= 1 and num_frequencies >= 0, got {in_dim}, {num_frequencies}")
        self.in_dim = in_dim
        self.num_frequencies = num_frequencies
        self.include_input = include_input
        # (L,) angular frequencies 2^k * pi
        self.register_buffer("frequencies", (2.0 ** torch.arange(num_frequencies)) * math.pi, persistent=False)

    @property
    def out_dim(self) -> int:
        return self.in_dim * (int(self.include_input) + 2 * self.num_frequencies)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        """(..., D) -> (..., out_dim)"""
        if x.shape[-1] != self.in_dim:
            raise ValueError(f"SinusoidalEncoding expected (..., {self.in_dim}) coordinates, got {tuple(x.shape)}")
        angles = x[..., None, :] * self.frequencies[:, None]  # (..., L, D)
        features = torch.cat([torch.sin(angles), torch.cos(angles)], dim=-1).flatten(-2)  # (..., L * 2D)
        return torch.cat([x, features], dim=-1) if self.include_input else features
