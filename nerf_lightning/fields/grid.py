"""Fast radiance fields: a grid encoding (hash grid or factorised grid) with two small MLPs (Instant-NGP's field)."""

from __future__ import annotations

import math
from collections.abc import Sequence

import torch
import torch.nn.functional as F
from torch import nn

from nerf_lightning.fields.appearance import AppearanceEmbedding
from nerf_lightning.fields.encodings import SinusoidalEncoding, SphericalHarmonicsEncoding
from nerf_lightning.fields.hash_grid import HashGridEncoding
from nerf_lightning.fields.mlp import MLP


class _TruncExp(torch.autograd.Function):
    """exp(x) whose gradient is exp(min(x, 15)): density stays positive and its gradient cannot blow up.

    Computed in float32 whatever ``x`` is: under 16-mixed precision exp(15) = 3.3e6 would overflow float16 (65504),
    so the density is float32 and the gradient is cast back to ``x``'s dtype only at the end."""

    @staticmethod
    def forward(ctx, x: torch.Tensor) -> torch.Tensor:  # noqa: D102
        ctx.save_for_backward(x)
        return torch.exp(x.float())

    @staticmethod
    def backward(ctx, grad: torch.Tensor) -> torch.Tensor:  # noqa: D102
        (x,) = ctx.saved_tensors
        return (grad.float() * torch.exp(x.float().clamp(max=15.0))).to(x.dtype)


def trunc_exp(x: torch.Tensor) -> torch.Tensor:
    """Elementwise exp with the gradient truncated at x = 15 (Instant-NGP's density activation)."""
    return _TruncExp.apply(x)


def check_aabb(aabb: Sequence[float], owner: str) -> torch.Tensor:
    """A box as 6 numbers (xmin, ymin, zmin, xmax, ymax, zmax) with min < max -> (6,) float32; ValueError otherwise."""
    box = torch.as_tensor(list(aabb), dtype=torch.float32)
    if box.shape != (6,) or not bool((box[3:] > box[:3]).all()):
        raise ValueError(f"{owner}: aabb must be 6 numbers (xmin, ymin, zmin, xmax, ymax, zmax) with min < max, got {box.tolist()}")
    return box


def grid_density(points: torch.Tensor, aabb: torch.Tensor, encoding: nn.Module, mlp: nn.Module) -> tuple[torch.Tensor, torch.Tensor]:
    """(..., 3) field-space points -> the density (...,) >= 0 (``trunc_exp`` of the MLP's first output, 0 outside the
    box ``aabb``) and the MLP's other outputs (..., K): the points normalised to the box's unit cube, encoded, the MLP."""
    unit = (points - aabb[:3]) / (aabb[3:] - aabb[:3])
    out = mlp(encoding(unit))
    inside = ((unit >= 0.0) & (unit <= 1.0)).all(dim=-1)
    return trunc_exp(out[..., 0]) * inside, out[..., 1:]


class DensityField(nn.Module):
    """Density only: a grid encoding and a small MLP, what a proposal sampler's proposal networks are (nerfacto's
    ``HashMLPDensityField``: a hash grid of a few levels, one hidden layer of 16).

    Args:
        aabb: the box in the field space, 6 numbers; encoding: (..., 3) in [0, 1] -> (..., out_dim);
        hidden_width: the MLP's hidden layer.
    """

    def __init__(self, aabb: Sequence[float], encoding: nn.Module, hidden_width: int = 16) -> None:
        super().__init__()
        self.register_buffer("aabb", check_aabb(aabb, type(self).__name__))
        self.encoding = encoding
        self.mlp = MLP(encoding.out_dim, hidden_width, 1, 1)

    def density(self, points: torch.Tensor) -> torch.Tensor:
        """(..., 3) field-space points -> (...,) densities >= 0, 0 outside the box."""
        return grid_density(points, self.aabb, self.encoding, self.mlp)[0]

    @torch.no_grad()
    def bake(self, resolution: int, chunk_size: int = 2**17) -> BakedDensity:
        """This field's log-density at the (R + 1)^3 vertices of a grid of ``resolution`` cells a side over its box,
        as a :class:`BakedDensity` (evaluation only: it does not learn). ``chunk_size`` vertices at a time."""
        ticks = torch.linspace(0.0, 1.0, resolution + 1, device=self.aabb.device)
        y, x = torch.meshgrid(ticks, ticks, indexing="ij")
        plane = torch.stack([x, y], dim=-1).reshape(-1, 2)  # one z slice's vertices, x fastest
        log_density = []
        for z in ticks.split(max(1, chunk_size // plane.shape[0])):  # z slowest: the dense grid's row order
            unit = torch.cat([plane.repeat(len(z), 1), z.repeat_interleave(plane.shape[0])[:, None]], dim=-1)
            log_density.append(self.mlp(self.encoding(unit))[..., 0].float())
        return BakedDensity(self.aabb, resolution, torch.cat(log_density))


class BakedDensity(nn.Module):
    """A density field read off a grid: the log-density at the (R + 1)^3 vertices of a grid of R cells a side over
    the box ``aabb``, trilinearly interpolated and exponentiated, 0 outside the box. What :meth:`DensityField.bake`
    makes of a proposal network for evaluation: one interpolation a point instead of a hash encoding and an MLP, at
    the price of the network's detail between the vertices. The interpolation is PyTorch's ``grid_sample`` (one
    vectorised kernel; on a CPU faster than the same interpolation as a one-level hash grid),
    except on an Apple GPU before torch 2.9, which has no 3D ``grid_sample``: there a one-level, one-feature
    :class:`~nerf_lightning.fields.hash_grid.HashGridEncoding` whose table holds the vertices densely interpolates
    them (the same values).

    Args:
        aabb: the box in the field space, (6,); resolution: R;
        log_density: ((R + 1)^3,) at the vertices, x fastest, then y, then z.
    """

    def __init__(self, aabb: torch.Tensor, resolution: int, log_density: torch.Tensor) -> None:
        super().__init__()
        side = resolution + 1
        if log_density.shape != (side**3,):
            raise ValueError(f"BakedDensity of resolution {resolution} expected ({side**3},) vertex log-densities, got {tuple(log_density.shape)}")
        self.register_buffer("aabb", aabb.detach().clone())
        # (1, 1, z, y, x): grid_sample's (N, C, D, H, W), whose sampling points are given as (x, y, z)
        self.register_buffer("log_density", log_density.detach().reshape(1, 1, side, side, side).clone())
        self._vertex_encoding: HashGridEncoding | None = None

    def density(self, points: torch.Tensor) -> torch.Tensor:
        """(..., 3) field-space points -> (...,) densities >= 0, 0 outside the box."""
        unit = (points - self.aabb[:3]) / (self.aabb[3:] - self.aabb[:3])
        inside = ((unit >= 0.0) & (unit <= 1.0)).all(dim=-1)
        if has_grid_sample_3d(self.log_density.device):
            # align_corners: -1 and 1 are the first and the last vertex; border: a point outside reads the nearest face
            grid = (2.0 * unit - 1.0).reshape(1, 1, 1, -1, 3).to(self.log_density.dtype)
            log_density = F.grid_sample(self.log_density, grid, mode="bilinear", padding_mode="border", align_corners=True)
            log_density = log_density.reshape(points.shape[:-1])
        else:
            log_density = self.vertex_encoding()(unit)[..., 0]
        return torch.exp(log_density) * inside

    def vertex_encoding(self) -> HashGridEncoding:
        """The vertices as a one-level, one-feature hash grid held densely (made once): the interpolation where
        ``grid_sample`` has no 3D kernel."""
        if self._vertex_encoding is None:
            resolution, vertices = self.log_density.shape[-1] - 1, self.log_density.numel()
            encoding = HashGridEncoding(n_levels=1, features_per_level=1, log2_table_size=math.ceil(math.log2(vertices)),
                                        base_resolution=resolution, max_resolution=resolution).to(self.log_density.device)
            encoding.table = nn.Parameter(self.log_density.reshape(-1, 1).clone(), requires_grad=False)
            self._vertex_encoding = encoding
        return self._vertex_encoding


def has_grid_sample_3d(device: torch.device) -> bool:
    """Whether ``grid_sample`` has a 3D kernel on ``device``: everywhere but an Apple GPU before torch 2.9."""
    return device.type != "mps" or torch.__version__ >= (2, 9)


class GridField(nn.Module):
    """Position -> grid encoding -> density MLP -> density and a geometry feature; feature + direction -> colour.

    Instant-NGP's field with ``encoding=HashGridEncoding(...)``, a TensoRF-style one with ``TensorVMEncoding(...)``.
    Field-space points are normalised to the unit cube by ``aabb`` (xmin, ymin, zmin, xmax, ymax, zmax) and encoded
    by ``encoding`` (any module (..., 3) in [0, 1] -> (..., out_dim)); outside the box the density is 0. (An
    unbounded scene's points arrive contracted into [-2, 2]^3, which its box covers: see
    :mod:`nerf_lightning.geometry.space`.) A one-hidden-layer MLP gives the density (through ``trunc_exp``) and a
    geometry feature; a colour MLP of ``colour_layers`` hidden layers takes that feature and the view direction's
    encoding to RGB (sigmoid).

    Args:
        aabb: the field's box in the field space, 6 numbers.
        encoding: the position encoding, with an ``out_dim``.
        hidden_width: width of both MLPs' hidden layers.
        geometry_features: width of the feature the density MLP hands the colour MLP.
        colour_layers: hidden layers of the colour MLP.
        direction_encoding: ``sh`` (spherical harmonics, 16 features) or ``sinusoidal`` (L = 4, 27 features).
        appearance_dim: > 0 gives every training image a learnt vector of this width that the colour MLP also
            sees (:class:`~nerf_lightning.fields.appearance.AppearanceEmbedding`, nerfacto's 32): colour may vary
            with the image's exposure, density may not. Views that are not training images get the mean vector.
        appearance_init: ``zeros`` or ``normal`` (nerfstudio's N(0, 1)): the vectors' start.
        appearance_penalty: weight of the vectors' mean squared norm in the loss (keeps the mean vector, which
            held-out views get, among the ones the colour MLP learnt from); 0 for none.
    """

    def __init__(
        self,
        aabb: Sequence[float],
        encoding: nn.Module,
        hidden_width: int = 64,
        geometry_features: int = 15,
        colour_layers: int = 2,
        direction_encoding: str = "sh",
        appearance_dim: int = 0,
        appearance_init: str = "zeros",
        appearance_penalty: float = 0.01,
    ) -> None:
        super().__init__()
        self.register_buffer("aabb", check_aabb(aabb, type(self).__name__))
        self.encoding = encoding
        self.density_mlp = MLP(encoding.out_dim, hidden_width, 1, 1 + geometry_features)
        if direction_encoding == "sh":
            self.direction_encoding: nn.Module = SphericalHarmonicsEncoding(4)
        elif direction_encoding == "sinusoidal":
            self.direction_encoding = SinusoidalEncoding(3, 4)
        else:
            raise ValueError(f"{type(self).__name__}: direction_encoding must be sh or sinusoidal, got '{direction_encoding}'")
        self.appearance = AppearanceEmbedding(appearance_dim, appearance_init, appearance_penalty) if appearance_dim > 0 else None
        self.colour_mlp = MLP(geometry_features + self.direction_encoding.out_dim + appearance_dim, hidden_width, colour_layers, 3)

    def density_and_feature(self, points: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """(..., 3) field-space points -> density (...,) >= 0 and the geometry feature (..., geometry_features)."""
        return grid_density(points, self.aabb, self.encoding, self.density_mlp)

    def density(self, points: torch.Tensor) -> torch.Tensor:
        """(..., 3) field-space points -> (...,) densities: what meshes and occupancy grids query."""
        return self.density_and_feature(points)[0]

    def forward(self, points: torch.Tensor, viewdirs: torch.Tensor, camera_indices: torch.Tensor | None = None) -> dict[str, torch.Tensor]:
        """field-space points (..., 3), unit view directions (..., 3) and, with an appearance embedding, the (...,)
        training image of each point (None: the mean appearance) -> ``rgb`` (..., 3) in (0, 1), ``density`` (...,) >= 0."""
        density, feature = self.density_and_feature(points)
        inputs = [feature, self.direction_encoding(viewdirs)]
        if self.appearance is not None:
            lead = points.shape[:-1]
            flat = None if camera_indices is None else camera_indices.reshape(-1)
            inputs.append(self.appearance(flat, lead.numel()).reshape(*lead, -1).to(feature.dtype))
        rgb = torch.sigmoid(self.colour_mlp(torch.cat(inputs, dim=-1)))
        return {"rgb": rgb, "density": density}
