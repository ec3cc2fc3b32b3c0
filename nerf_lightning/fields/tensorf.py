"""A TensoRF-style factorised grid (Chen et al. 2022, the vector-matrix decomposition) as an encoding.

A dense R^3 x C feature grid is replaced by, for each axis a of (x, y, z), C matrices over the plane of the other
two axes and C vectors along a:

    feature_(a, c)(p) = M_(a, c)(p_plane(a)) * v_(a, c)(p_a)        (bilinear and linear interpolation)

concatenated into 3C features. A point costs 6 interpolations (3 bilinear, 3 linear) against the hash grid's
8 lookups a level, and the parameters grow with R^2 instead of R^3.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import nn

# for each axis a: the two plane axes and the line axis
PLANE_AXES = ((1, 2), (0, 2), (0, 1))
LINE_AXES = (0, 1, 2)


class TensorVMEncoding(nn.Module):
    """Vector-matrix factorised grid over the unit cube.

    Args:
        resolution: R, samples a side of the matrices and vectors.
        components: C, components per axis; the output has 3C features.
        init_scale: the factors start normal with this standard deviation.

    ``forward``: (..., 3) points in [0, 1] (clamped) -> (..., 3C).
    """

    def __init__(self, resolution: int = 128, components: int = 16, init_scale: float = 0.1) -> None:
        super().__init__()
        if resolution < 2 or components < 1:
            raise ValueError(f"TensorVMEncoding needs resolution >= 2 and components >= 1, got {resolution}, {components}")
        self.resolution, self.components = resolution, components
        self.planes = nn.Parameter(init_scale * torch.randn(3, components, resolution, resolution))  # (3, C, R, R)
        self.lines = nn.Parameter(init_scale * torch.randn(3, components, resolution, 1))  # (3, C, R, 1)

    @property
    def out_dim(self) -> int:
        return 3 * self.components

    def forward(self, points: torch.Tensor) -> torch.Tensor:
        """(..., 3) points in [0, 1] -> (..., 3C)"""
        if points.shape[-1] != 3:
            raise ValueError(f"TensorVMEncoding expected (..., 3) points, got {tuple(points.shape)}")
        lead = points.shape[:-1]
        coords = points.reshape(-1, 3).clamp(0.0, 1.0) * 2.0 - 1.0  # grid_sample's [-1, 1]
        # grid_sample takes (x, y) = (column, row): a plane's first axis runs along its columns
        plane_grid = torch.stack([coords[:, list(axes)] for axes in PLANE_AXES])[:, :, None, :]  # (3, M, 1, 2)
        line_grid = torch.stack([torch.stack([torch.zeros_like(coords[:, a]), coords[:, a]], dim=-1) for a in LINE_AXES])[:, :, None, :]
        plane_features = F.grid_sample(self.planes, plane_grid, mode="bilinear", align_corners=True)  # (3, C, M, 1)
        line_features = F.grid_sample(self.lines, line_grid, mode="bilinear", align_corners=True)  # (3, C, M, 1)
        features = (plane_features * line_features)[..., 0]  # (3, C, M)
        return features.permute(2, 0, 1).reshape(*lead, self.out_dim)
