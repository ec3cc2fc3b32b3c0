"""Mip-NeRF 360's scene contraction: all of space into a cube, so that a grid can hold an unbounded scene.

Points in [-1, 1]^3 stay as they are, and every point x beyond moves to (2 - 1 / |x|) x / |x|, so that all of
space up to infinity fits in [-2, 2]^3. The norm is the max-norm (nerfstudio's ``SceneContraction(order=inf)``),
so the contracted space is a cube that a grid fills without waste: the inner box keeps the middle half of each
axis, the rest holds the background at a resolution that falls off as 1 / distance. The loaders of real captures
put the cameras inside [-1, 1]^3, so the inner box is where the subject is.
"""

from __future__ import annotations

import torch


def contract(x: torch.Tensor) -> torch.Tensor:
    """(..., 3) points -> (..., 3) in [-2, 2]^3: unchanged where |x|_inf <= 1, else (2 - 1/|x|) x/|x| (max-norm)."""
    norm = x.abs().amax(dim=-1, keepdim=True)
    safe = norm.clamp(min=1.0)
    return torch.where(norm <= 1.0, x, (2.0 - 1.0 / safe) * x / safe)


def uncontract(y: torch.Tensor) -> torch.Tensor:
    """The inverse of :func:`contract`: (..., 3) points in (-2, 2)^3 -> (..., 3) points (|y|_inf must stay below 2)."""
    norm = y.abs().amax(dim=-1, keepdim=True)
    safe = norm.clamp(min=1.0, max=2.0 - 1e-6)
    return torch.where(norm <= 1.0, y, y / safe / (2.0 - safe))


class Contraction:
    """The contraction as an object a point is passed through (see the module's docstring).

    ``contraction(points)`` maps (..., 3) scene points to (..., 3) points in :attr:`bounds`; ``inverse`` undoes it.
    A field or an occupancy grid of a contracted scene covers :attr:`bounds`, the cube [-2, 2]^3, and the part of
    the scene kept at full resolution, where the map is the identity, is :attr:`identity_box`, [-1, 1]^3.
    """

    bounds = (-2.0, -2.0, -2.0, 2.0, 2.0, 2.0)
    identity_box = (-1.0, -1.0, -1.0, 1.0, 1.0, 1.0)

    def __call__(self, points: torch.Tensor) -> torch.Tensor:
        return contract(points)

    def inverse(self, points: torch.Tensor) -> torch.Tensor:
        return uncontract(points)

    def __repr__(self) -> str:
        return "Contraction(max-norm, [-1, 1]^3 kept, all of space into [-2, 2]^3)"
