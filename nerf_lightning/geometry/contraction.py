"""From the world to a grid's unit cube: a bounded box, or an unbounded scene contracted (Mip-NeRF 360).

A grid (hash encoding, factorised grid, occupancy grid) covers the unit cube [0, 1]^3. A bounded scene maps its
box ``aabb`` onto it linearly, and nothing outside the box exists. An unbounded scene (a real capture with its
background) is *contracted*: the box is first mapped to [-1, 1]^3, where points stay as they are, and every point
x beyond it moves to (2 - 1 / |x|) x / |x|, so that all of space up to infinity fits in [-2, 2]^3, which then maps
to the unit cube. The norm is the max-norm (nerfstudio's ``SceneContraction(order=inf)``), so the contracted space
is a cube that a grid fills without waste. The box keeps the middle half of each axis; the rest of the grid holds
the background at a resolution that falls off as 1 / distance.
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


def world_to_unit(points: torch.Tensor, aabb: torch.Tensor, contracted: bool = False) -> torch.Tensor:
    """(..., 3) world points -> (..., 3) coordinates in the grid's unit cube.

    ``aabb`` (6,): the box (xmin, ymin, zmin, xmax, ymax, zmax). Bounded: the box maps onto [0, 1]^3 and points
    outside it fall outside [0, 1]. ``contracted``: the box maps onto [0.25, 0.75]^3 and all of space into [0, 1]^3.
    """
    low, high = aabb[:3], aabb[3:]
    if not contracted:
        return (points - low) / (high - low)
    return (contract(2.0 * (points - low) / (high - low) - 1.0) + 2.0) / 4.0


def unit_to_world(unit: torch.Tensor, aabb: torch.Tensor, contracted: bool = False) -> torch.Tensor:
    """The inverse of :func:`world_to_unit`: (..., 3) coordinates in the unit cube -> (..., 3) world points."""
    low, high = aabb[:3], aabb[3:]
    if not contracted:
        return low + unit * (high - low)
    return low + (uncontract(4.0 * unit - 2.0) + 1.0) * 0.5 * (high - low)
