"""Fast radiance fields: a grid encoding (hash grid or factorised grid) with two small MLPs (Instant-NGP's field)."""

from __future__ import annotations

from collections.abc import Sequence

import torch
from torch import nn

from nerf_lightning.fields.encodings import SinusoidalEncoding, SphericalHarmonicsEncoding
from nerf_lightning.fields.hash_grid import HashGridEncoding
from nerf_lightning.fields.mlp import MLP
from nerf_lightning.geometry.contraction import world_to_unit


class _TruncExp(torch.autograd.Function):
    """exp(x) whose gradient is exp(min(x, 15)): density stays positive and its gradient cannot blow up."""

    @staticmethod
    def forward(ctx, x: torch.Tensor) -> torch.Tensor:  # noqa: D102
        ctx.save_for_backward(x)
        return torch.exp(x)

    @staticmethod
    def backward(ctx, grad: torch.Tensor) -> torch.Tensor:  # noqa: D102
        (x,) = ctx.saved_tensors
        return grad * torch.exp(x.clamp(max=15.0))


def trunc_exp(x: torch.Tensor) -> torch.Tensor:
    """Elementwise exp with the gradient truncated at x = 15 (Instant-NGP's density activation)."""
    return _TruncExp.apply(x)


class GridField(nn.Module):
    """Position -> grid encoding -> density MLP -> density and a geometry feature; feature + direction -> colour.

    Points are normalised to the unit cube by ``aabb`` (xmin, ymin, zmin, xmax, ymax, zmax) and encoded by
    ``encoding`` (any module (..., 3) in [0, 1] -> (..., out_dim)); outside the box the density is 0, unless the
    field is ``contracted`` (an unbounded scene: all of space is contracted into the cube around the box, see
    :mod:`nerf_lightning.geometry.contraction`). A
    one-hidden-layer MLP gives the density (through ``trunc_exp``) and a geometry feature; a colour MLP of
    ``colour_layers`` hidden layers takes that feature and the view direction's encoding to RGB (sigmoid).

    Args:
        aabb: the scene's bounding box, 6 numbers.
        encoding: the position encoding, with an ``out_dim``.
        hidden_width: width of both MLPs' hidden layers.
        geometry_features: width of the feature the density MLP hands the colour MLP.
        colour_layers: hidden layers of the colour MLP.
        direction_encoding: ``sh`` (spherical harmonics, 16 features) or ``sinusoidal`` (L = 4, 27 features).
        contracted: model all of space, the box at full resolution and the rest contracted around it.
    """

    def __init__(
        self,
        aabb: Sequence[float],
        encoding: nn.Module,
        hidden_width: int = 64,
        geometry_features: int = 15,
        colour_layers: int = 2,
        direction_encoding: str = "sh",
        contracted: bool = False,
    ) -> None:
        super().__init__()
        self.contracted = contracted
        aabb = torch.as_tensor(list(aabb), dtype=torch.float32)
        if aabb.shape != (6,) or not bool((aabb[3:] > aabb[:3]).all()):
            raise ValueError(f"{type(self).__name__}: aabb must be 6 numbers (xmin, ymin, zmin, xmax, ymax, zmax) with min < max, got {aabb.tolist()}")
        self.register_buffer("aabb", aabb)
        self.encoding = encoding
        self.density_mlp = MLP(encoding.out_dim, hidden_width, 1, 1 + geometry_features)
        if direction_encoding == "sh":
            self.direction_encoding: nn.Module = SphericalHarmonicsEncoding(4)
        elif direction_encoding == "sinusoidal":
            self.direction_encoding = SinusoidalEncoding(3, 4)
        else:
            raise ValueError(f"{type(self).__name__}: direction_encoding must be sh or sinusoidal, got '{direction_encoding}'")
        self.colour_mlp = MLP(geometry_features + self.direction_encoding.out_dim, hidden_width, colour_layers, 3)

    def density_and_feature(self, points: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """(..., 3) points -> density (...,) >= 0 and the geometry feature (..., geometry_features)."""
        unit = world_to_unit(points, self.aabb, self.contracted)
        out = self.density_mlp(self.encoding(unit))
        density = trunc_exp(out[..., 0])
        if not self.contracted:
            density = density * ((unit >= 0.0) & (unit <= 1.0)).all(dim=-1)
        return density, out[..., 1:]

    def density(self, points: torch.Tensor) -> torch.Tensor:
        """(..., 3) points -> (...,) densities: what meshes and occupancy grids query."""
        return self.density_and_feature(points)[0]

    def forward(self, points: torch.Tensor, directions: torch.Tensor) -> dict[str, torch.Tensor]:
        """points (..., 3), unit view directions (..., 3) -> ``rgb`` (..., 3) in (0, 1), ``density`` (...,) >= 0."""
        density, feature = self.density_and_feature(points)
        rgb = torch.sigmoid(self.colour_mlp(torch.cat([feature, self.direction_encoding(directions)], dim=-1)))
        return {"rgb": rgb, "density": density}


class HashGridField(GridField):
    """Instant-NGP's field: a :class:`GridField` on a multiresolution hash encoding.

    ``n_levels``, ``features_per_level``, ``log2_table_size``, ``base_resolution``, ``max_resolution``: the hash
    grid's sizes (see :class:`~nerf_lightning.fields.hash_grid.HashGridEncoding`); the rest as in :class:`GridField`.
    """

    def __init__(
        self,
        aabb: Sequence[float],
        n_levels: int = 16,
        features_per_level: int = 2,
        log2_table_size: int = 19,
        base_resolution: int = 16,
        max_resolution: int = 2048,
        hidden_width: int = 64,
        geometry_features: int = 15,
        colour_layers: int = 2,
        direction_encoding: str = "sh",
        contracted: bool = False,
    ) -> None:
        encoding = HashGridEncoding(n_levels, features_per_level, log2_table_size, base_resolution, max_resolution)
        super().__init__(aabb, encoding, hidden_width, geometry_features, colour_layers, direction_encoding, contracted)
