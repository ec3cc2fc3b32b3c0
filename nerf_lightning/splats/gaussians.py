"""The Gaussians a splat model learns, as 3DGS stores them: means, unit quaternions (w, x, y, z), log scales, opacity
logits and spherical-harmonic colours (``sh0``: degree 0; ``shN``: the higher bands up to ``sh_degree``).

Every parameter changes size in training (densification): they are the module's ``variable_size_parameters``, so a
checkpoint loads at the size it was saved with, and a strategy edits them only through :meth:`Gaussians.edit`,
which keeps the optimiser's state in step (:func:`~nerf_lightning.parameters.groups.replace_parameter`).
"""

from __future__ import annotations

import logging
import math
from collections.abc import Callable

import torch
from torch import nn

from nerf_lightning.splats.projection import inverse_sigmoid
from nerf_lightning.splats.sh import coefficients_for, rgb_to_sh, rotate_sh

log = logging.getLogger(__name__)

PARAMETERS = ("means", "quats", "log_scales", "opacity_logits", "sh0", "shN")


class Gaussians(nn.Module):
    """N Gaussians (N = 0 until :meth:`initialise`): ``means`` (N, 3), ``quats`` (N, 4), ``log_scales`` (N, 3),
    ``opacity_logits`` (N,), ``sh0`` (N, 1, 3), ``shN`` (N, (sh_degree + 1)^2 - 1, 3).

    Args:
        sh_degree: the highest spherical-harmonic degree of the colours (0 to 3).
        initial_opacity: every Gaussian's opacity at the start (3DGS: 0.1).
        initial_scale: every Gaussian's scale at the start, as a multiple of the mean distance to its 3 nearest
            neighbours (3DGS: 1). Below 1, a random start covers each pixel with fewer Gaussians: fewer
            (Gaussian, pixel) pairs to draw while densification has not yet shaped them.
        sh_degree_interval: in training the colours' degree goes up by one every so many steps, to ``sh_degree``
            (:meth:`degree_at`; 3DGS's 1000).
    """

    variable_size_parameters = PARAMETERS

    def __init__(self, sh_degree: int = 3, initial_opacity: float = 0.1, initial_scale: float = 1.0,
                 sh_degree_interval: int = 1000) -> None:
        super().__init__()
        if not 0 <= sh_degree <= 3:
            raise ValueError(f"model.gaussians.sh_degree must be 0 to 3, got {sh_degree}")
        if initial_scale <= 0:
            raise ValueError(f"model.gaussians.initial_scale must be > 0, got {initial_scale}")
        self.sh_degree, self.initial_opacity, self.initial_scale = sh_degree, initial_opacity, initial_scale
        self.sh_degree_interval = sh_degree_interval
        higher = coefficients_for(sh_degree) - 1
        for name, shape in zip(PARAMETERS, ((0, 3), (0, 4), (0, 3), (0,), (0, 1, 3), (0, higher, 3))):
            setattr(self, name, nn.Parameter(torch.zeros(shape)))

    def __len__(self) -> int:
        return int(self.means.shape[0])

    def degree_at(self, step: int) -> int:
        """The colours' degree at training step ``step``: one more every ``sh_degree_interval`` steps, to ``sh_degree``."""
        return min(step // max(self.sh_degree_interval, 1), self.sh_degree)

    @property
    def opacities(self) -> torch.Tensor:
        """(N,) in (0, 1)."""
        return torch.sigmoid(self.opacity_logits)

    @property
    def coefficients(self) -> torch.Tensor:
        """(N, (sh_degree + 1)^2, 3) every band's coefficients."""
        return torch.cat([self.sh0, self.shN], dim=1)

    @torch.no_grad()
    def initialise(self, positions: torch.Tensor, colours: torch.Tensor, generator: torch.Generator | None = None,
                   scale: float | torch.Tensor | None = None) -> None:
        """Start from (N, 3) ``positions`` with (N, 3) ``colours`` in [0, 1]: each Gaussian round, its scale
        ``scale`` (a number, or (N,) one a Gaussian; None: ``initial_scale``) times the mean distance to its 3 nearest
        neighbours (3DGS's), a random rotation, opacity ``initial_opacity``."""
        n = positions.shape[0]
        device = self.means.device
        positions, colours = positions.to(device, torch.float32), colours.to(device, torch.float32)
        scale = torch.as_tensor(self.initial_scale if scale is None else scale, dtype=torch.float32, device=device)
        if scale.ndim > 1 or (scale.ndim == 1 and len(scale) != n) or not bool((scale > 0).all()):
            raise ValueError(f"a Gaussian's start scale must be > 0, one number or one a Gaussian ({n}), got {tuple(scale.shape)} "
                             f"from {float(scale.min()) if scale.numel() else 'none'}")
        distances = scale * nearest_neighbour_distances(positions, 3).mean(dim=-1).clamp(min=1e-7)
        values = {
            "means": positions,
            "quats": torch.nn.functional.normalize(torch.randn(n, 4, generator=generator).to(device), dim=-1),
            "log_scales": torch.log(distances)[:, None].repeat(1, 3),
            "opacity_logits": torch.full((n,), inverse_sigmoid(self.initial_opacity), device=device),
            "sh0": rgb_to_sh(colours)[:, None, :],
            "shN": torch.zeros(n, self.shN.shape[1], 3, device=device),
        }
        for name, value in values.items():
            setattr(self, name, nn.Parameter(value))

    def edit(self, values: dict[str, torch.Tensor], rows_from: torch.Tensor,
             replace: Callable[[nn.Module, str, torch.Tensor, torch.Tensor | None], nn.Parameter]) -> None:
        """Replace every parameter by ``values[name]`` (N_new rows each), its optimiser state carried by ``rows_from``
        (N_new,): the old row each new row continues, or -1 for a fresh one (zeros). ``replace`` is the model's
        :meth:`~nerf_lightning.models.base.FieldModule.replace_parameter`."""
        if set(values) != set(PARAMETERS) or any(len(value) != len(rows_from) for value in values.values()):
            raise ValueError(f"Gaussians.edit needs {', '.join(PARAMETERS)}, each of {len(rows_from)} rows, got "
                             f"{ {name: tuple(value.shape) for name, value in values.items()} }")
        for name in PARAMETERS:
            replace(self, name, values[name].detach(), rows_from)


def nearest_neighbour_distances(points: torch.Tensor, k: int, chunk: int = 1024) -> torch.Tensor:
    """(N, 3) points -> (N, k) distances to each point's k nearest others (fewer than k + 1 points: as many as there
    are, padded with the largest), computed ``chunk`` rows at a time so memory stays at chunk x N."""
    n = points.shape[0]
    if n < 2:
        return torch.ones(n, k, device=points.device)
    found = []
    for rows in points.split(chunk):
        distances = torch.cdist(rows, points)  # (chunk, N)
        nearest = distances.topk(min(k + 1, n), largest=False).values[:, 1:]  # the point itself is the nearest
        if nearest.shape[1] < k:
            nearest = torch.cat([nearest, nearest[:, -1:].expand(-1, k - nearest.shape[1])], dim=1)
        found.append(nearest)
    return torch.cat(found)


def transform_gaussians(parameters: dict[str, torch.Tensor], matrix: torch.Tensor) -> dict[str, torch.Tensor]:
    """Gaussians as :meth:`~nerf_lightning.models.contract.HasGaussians.gaussian_parameters` gives them, moved by a
    similarity ``matrix`` (4, 4) (x -> s R x + t, s > 0): means moved, rotations composed with R, log scales + log s,
    the higher SH bands turned with R (:func:`~nerf_lightning.splats.sh.rotate_sh`); opacities and sh0 as they were.
    Computed in float64 on the CPU, returned there in the parameters' dtype."""
    from kornia.geometry.conversions import rotation_matrix_to_quaternion

    matrix = matrix.detach().cpu().to(torch.float64)
    parameters = {name: value.detach().cpu() for name, value in parameters.items()}
    linear, translation = matrix[:3, :3], matrix[:3, 3]
    determinant = float(torch.linalg.det(linear))
    scale = determinant ** (1.0 / 3.0) if determinant > 0 else 0.0  # a mirror (or a collapse) is no similarity
    rotation = linear / scale if scale > 0 else linear
    if not (scale > 0 and torch.allclose(rotation @ rotation.T, torch.eye(3, dtype=torch.float64), atol=1e-5)):
        raise ValueError(f"transform_gaussians needs a similarity (a scaled rotation and a translation), got\n{matrix}")
    dtype = parameters["means"].dtype
    means = parameters["means"].to(torch.float64) @ linear.T + translation
    turn = rotation_matrix_to_quaternion(rotation[None])[0]  # (w, x, y, z)
    quats = quaternion_product(turn.expand(len(means), 4), torch.nn.functional.normalize(parameters["quats"].to(torch.float64), dim=-1))
    out = dict(parameters)
    out.update(means=means.to(dtype), quats=quats.to(dtype), log_scales=(parameters["log_scales"] + math.log(scale)).to(dtype),
               shN=rotate_sh(parameters["shN"].to(torch.float64), rotation).to(dtype))
    return out


def quaternion_product(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """(N, 4) x (N, 4) -> (N, 4) Hamilton products a b of (w, x, y, z) quaternions: the rotation b, then a."""
    aw, ax, ay, az = a.unbind(-1)
    bw, bx, by, bz = b.unbind(-1)
    return torch.stack([aw * bw - ax * bx - ay * by - az * bz, aw * bx + ax * bw + ay * bz - az * by,
                        aw * by - ax * bz + ay * bw + az * bx, aw * bz + ax * by - ay * bx + az * bw], dim=-1)
