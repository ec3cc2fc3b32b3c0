"""A TensoRF-style factorised grid (Chen et al. 2022, the vector-matrix decomposition) as an encoding.

A dense R^3 x C feature grid is replaced by, for each axis a of (x, y, z), C matrices over the plane of the other
two axes and C vectors along a:

    feature_(a, c)(p) = M_(a, c)(p_plane(a)) * v_(a, c)(p_a)        (bilinear and linear interpolation)

concatenated into 3C features. A point costs 6 interpolations (3 bilinear, 3 linear) against the hash grid's
8 lookups a level, and the parameters grow with R^2 instead of R^3.

The interpolation is ``grid_sample``; on an Apple GPU, whose ``grid_sample`` has no backward kernel, the same
bilinear interpolation is done with ``gather`` (:func:`bilinear_gather`), whose backward MPS has.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import nn

# for each axis a: the two plane axes and the line axis
PLANE_AXES = ((1, 2), (0, 2), (0, 1))
LINE_AXES = (0, 1, 2)


def bilinear_gather(grids: torch.Tensor, xy: torch.Tensor) -> torch.Tensor:
    """``F.grid_sample(grids, xy[:, :, None], mode="bilinear", align_corners=True)`` written with ``gather``.

    grids (B, C, H, W); xy (B, M, 2) in [-1, 1] as (column, row) -> (B, C, M, 1). Differentiable in ``grids``
    (gather's backward is a scatter-add), for devices without grid_sample's backward (MPS)."""
    batch, channels, height, width = grids.shape
    x = (xy[..., 0].clamp(-1.0, 1.0) + 1.0) * 0.5 * (width - 1)  # (B, M)
    y = (xy[..., 1].clamp(-1.0, 1.0) + 1.0) * 0.5 * (height - 1)
    x0, y0 = x.floor().clamp(0, max(width - 2, 0)), y.floor().clamp(0, max(height - 2, 0))
    fx, fy = (x - x0)[:, None], (y - y0)[:, None]  # (B, 1, M)
    x0, y0 = x0.long(), y0.long()
    x1, y1 = (x0 + 1).clamp(max=width - 1), (y0 + 1).clamp(max=height - 1)
    flat = grids.flatten(2)  # (B, C, H*W)

    def at(rows: torch.Tensor, cols: torch.Tensor) -> torch.Tensor:
        return torch.gather(flat, 2, (rows * width + cols)[:, None, :].expand(batch, channels, -1))  # (B, C, M)

    top = at(y0, x0) * (1 - fx) + at(y0, x1) * fx
    bottom = at(y1, x0) * (1 - fx) + at(y1, x1) * fx
    return (top * (1 - fy) + bottom * fy)[..., None]


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
        if points.device.type == "mps":  # grid_sample has no backward kernel there
            plane_features, line_features = bilinear_gather(self.planes, plane_grid[:, :, 0]), bilinear_gather(self.lines, line_grid[:, :, 0])
        else:
            plane_features = F.grid_sample(self.planes, plane_grid, mode="bilinear", align_corners=True)  # (3, C, M, 1)
            line_features = F.grid_sample(self.lines, line_grid, mode="bilinear", align_corners=True)  # (3, C, M, 1)
        features = (plane_features * line_features)[..., 0]  # (3, C, M)
        return features.permute(2, 0, 1).reshape(*lead, self.out_dim)
