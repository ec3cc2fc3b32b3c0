"""View-dependent colour from real spherical harmonics up to degree 3, as 3D Gaussian splatting stores it.

A Gaussian keeps (degree + 1)^2 RGB coefficients; its colour seen along unit direction d (from the camera to the
Gaussian) is sum_k c_k Y_k(d) + 0.5, clamped at 0: the 0.5 makes coefficients of zero a mid grey, and the degree-0
coefficient c_0 = (rgb - 0.5) / Y_0 gives a constant colour rgb. The constants are those of 3DGS's and gsplat's
``SH_C0`` .. ``SH_C3`` (the real spherical harmonics' normalisations, signs as theirs), so that a PLY file exported
here shows the same colours in their viewers.
"""

from __future__ import annotations

import math

import torch

SH_C0 = 0.28209479177387814
SH_C1 = 0.4886025119029199
SH_C2 = (1.0925484305920792, -1.0925484305920792, 0.31539156525252005, -1.0925484305920792, 0.5462742152960396)
SH_C3 = (-0.5900435899266435, 2.890611442640554, -0.4570457994644658, 0.3731763325901154, -0.4570457994644658,
         1.445305721320277, -0.5900435899266435)


def coefficients_for(degree: int) -> int:
    """(degree + 1)^2, the coefficients a colour of that degree has."""
    return (degree + 1) ** 2


def rgb_to_sh(rgb: torch.Tensor) -> torch.Tensor:
    """(..., 3) colours in [0, 1] -> (..., 3) degree-0 coefficients that give them from every direction."""
    return (rgb - 0.5) / SH_C0


def sh_basis(degree: int, directions: torch.Tensor) -> torch.Tensor:
    """(N, 3) directions (normalised here) -> (N, (degree + 1)^2) the real spherical harmonics Y_k(d) of every band
    up to ``degree`` (0 to 3), 3DGS's constants and signs."""
    x, y, z = torch.nn.functional.normalize(directions, dim=-1).unbind(-1)
    basis = [torch.full_like(x, SH_C0)]
    if degree > 0:
        basis += [-SH_C1 * y, SH_C1 * z, -SH_C1 * x]
    if degree > 1:
        xx, yy, zz, xy, yz, xz = x * x, y * y, z * z, x * y, y * z, x * z
        basis += [SH_C2[0] * xy, SH_C2[1] * yz, SH_C2[2] * (2.0 * zz - xx - yy), SH_C2[3] * xz, SH_C2[4] * (xx - yy)]
    if degree > 2:
        basis += [SH_C3[0] * y * (3.0 * xx - yy), SH_C3[1] * xy * z, SH_C3[2] * y * (4.0 * zz - xx - yy),
                  SH_C3[3] * z * (2.0 * zz - 3.0 * xx - 3.0 * yy), SH_C3[4] * x * (4.0 * zz - xx - yy),
                  SH_C3[5] * z * (xx - yy), SH_C3[6] * x * (xx - 3.0 * yy)]
    return torch.stack(basis, dim=-1)


def sh_to_rgb(sh0: torch.Tensor) -> torch.Tensor:
    """(..., 3) degree-0 coefficients -> (..., 3) the colour they give from every direction (:func:`rgb_to_sh`'s
    inverse; not clamped)."""
    return SH_C0 * sh0 + 0.5


def spherical_harmonics(degree: int, coefficients: torch.Tensor, directions: torch.Tensor) -> torch.Tensor:
    """Colours of N Gaussians: ``coefficients`` (N, K, 3) with K >= (degree + 1)^2 (the first (degree + 1)^2 are
    used), ``directions`` (N, 3) (normalised here) -> (N, 3), clamped at 0. ``degree`` 0 to 3."""
    if not 0 <= degree <= 3 or coefficients.shape[1] < coefficients_for(degree):
        raise ValueError(f"spherical_harmonics of degree {degree} needs 0 <= degree <= 3 and (N, >= {coefficients_for(degree)}, 3) "
                         f"coefficients, got {tuple(coefficients.shape)}")
    if degree == 0:
        return sh_to_rgb(coefficients[:, 0]).clamp(min=0.0)
    basis = sh_basis(degree, directions)  # (N, (degree + 1)^2)
    colour = (basis[..., None] * coefficients[:, : coefficients_for(degree)]).sum(dim=1)
    return (colour + 0.5).clamp(min=0.0)


def rotate_sh(coefficients: torch.Tensor, rotation: torch.Tensor) -> torch.Tensor:
    """The higher bands' coefficients (N, K - 1, 3) (degrees 1 to 3, as ``shN``) of colours turned by ``rotation``
    (3, 3): the rotated colours seen along R d are the old ones seen along d.

    Each band l is a (2l + 1)-dimensional space that rotations map to itself; its matrix is found by evaluating the
    band at 64 fixed directions d and at R d and solving the least squares (exact: the band is the same space at both),
    instead of writing out Wigner's D matrices."""
    if coefficients.shape[1] == 0:
        return coefficients
    degree = math.isqrt(coefficients.shape[1] + 1) - 1  # K - 1 = (degree + 1)^2 - 1
    directions = torch.nn.functional.normalize(torch.randn(64, 3, generator=torch.Generator().manual_seed(0), dtype=torch.float64), dim=-1)
    rotation = rotation.detach().to("cpu", torch.float64)
    at_d, at_rotated = sh_basis(degree, directions), sh_basis(degree, directions @ rotation.T)  # (64, K)
    rotated = []
    for band in range(1, degree + 1):
        columns = slice(band * band, (band + 1) * (band + 1))
        # coefficients c' with Y(R d) c' = Y(d) c for every d: c' = M c
        matrix = torch.linalg.lstsq(at_rotated[:, columns], at_d[:, columns]).solution  # (2l + 1, 2l + 1)
        part = coefficients[:, columns.start - 1 : columns.stop - 1]
        rotated.append(torch.einsum("ij,njc->nic", matrix.to(part), part))
    return torch.cat(rotated, dim=1)
