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


class SphericalHarmonicsEncoding(nn.Module):
    """Real spherical harmonics of a unit direction up to degree ``degree - 1`` (Instant-NGP's direction encoding).

    (..., 3) unit vectors -> (..., degree**2) features; ``degree`` 1 to 4 (1, 4, 9 or 16 features). The
    constants are those of the real, orthonormal basis (as in tiny-cuda-nn and nerfstudio).
    """

    def __init__(self, degree: int = 4) -> None:
        super().__init__()
        if not 1 <= degree <= 4:
            raise ValueError(f"SphericalHarmonicsEncoding degree must be 1 to 4, got {degree}")
        self.degree = degree

    @property
    def out_dim(self) -> int:
        return self.degree**2

    def forward(self, directions: torch.Tensor) -> torch.Tensor:
        """(..., 3) -> (..., degree**2)"""
        if directions.shape[-1] != 3:
            raise ValueError(f"SphericalHarmonicsEncoding expected (..., 3) directions, got {tuple(directions.shape)}")
        x, y, z = directions.unbind(-1)
        terms = [torch.full_like(x, 0.28209479177387814)]
        if self.degree > 1:
            terms += [-0.48860251190291987 * y, 0.48860251190291987 * z, -0.48860251190291987 * x]
        if self.degree > 2:
            xx, yy, zz = x * x, y * y, z * z
            terms += [
                1.0925484305920792 * x * y, -1.0925484305920792 * y * z, 0.94617469575755997 * zz - 0.31539156525251999,
                -1.0925484305920792 * x * z, 0.54627421529603959 * (xx - yy),
            ]
        if self.degree > 3:
            terms += [
                0.59004358992664352 * y * (3 * xx - yy), 2.8906114426405538 * x * y * z, 0.45704579946446572 * y * (1 - 5 * zz),
                0.3731763325901154 * z * (5 * zz - 3), 0.45704579946446572 * x * (1 - 5 * zz), 1.4453057213202769 * z * (xx - yy),
                0.59004358992664352 * x * (xx - 3 * yy),
            ]
        return torch.stack(terms, dim=-1)
