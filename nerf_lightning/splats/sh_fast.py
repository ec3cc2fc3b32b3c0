"""Spherical-harmonic colour in numba, forward and backward: the colour step of the fused projection
(:mod:`~nerf_lightning.splats.projection_fast`), held equal to the readable reference
:func:`~nerf_lightning.splats.sh.spherical_harmonics` (tests/splats/test_projection_fast.py). Helpers inlined into
its loops: no call a Gaussian."""

from __future__ import annotations

import numba
import numpy as np

from nerf_lightning.splats.sh import SH_C0, SH_C1, SH_C2, SH_C3


@numba.njit(inline="always")
def sh_colour(degree, sh0, shN, g, x, y, z, channel):
    """One channel of Gaussian g's colour seen along the unit direction (x, y, z): sum_k c_k Y_k + 0.5, clamped at 0
    (:func:`~nerf_lightning.splats.sh.sh_basis`'s constants and signs)."""
    colour = SH_C0 * sh0[g, 0, channel]
    if degree > 0:
        colour += -SH_C1 * y * shN[g, 0, channel] + SH_C1 * z * shN[g, 1, channel] - SH_C1 * x * shN[g, 2, channel]
    if degree > 1:
        xx, yy, zz, xy, yz, xz = x * x, y * y, z * z, x * y, y * z, x * z
        colour += (SH_C2[0] * xy * shN[g, 3, channel] + SH_C2[1] * yz * shN[g, 4, channel]
                   + SH_C2[2] * (2.0 * zz - xx - yy) * shN[g, 5, channel] + SH_C2[3] * xz * shN[g, 6, channel]
                   + SH_C2[4] * (xx - yy) * shN[g, 7, channel])
        if degree > 2:
            colour += (SH_C3[0] * y * (3.0 * xx - yy) * shN[g, 8, channel] + SH_C3[1] * xy * z * shN[g, 9, channel]
                       + SH_C3[2] * y * (4.0 * zz - xx - yy) * shN[g, 10, channel]
                       + SH_C3[3] * z * (2.0 * zz - 3.0 * xx - 3.0 * yy) * shN[g, 11, channel]
                       + SH_C3[4] * x * (4.0 * zz - xx - yy) * shN[g, 12, channel]
                       + SH_C3[5] * z * (xx - yy) * shN[g, 13, channel] + SH_C3[6] * x * (xx - 3.0 * yy) * shN[g, 14, channel])
    return max(colour + 0.5, 0.0)


@numba.njit(inline="always", error_model="numpy")
def _band2_backward(shN, g, channel, grad, dx, dy, dz, gdx, gdy, gdz, grad_shN):
    """Band 2's part of :func:`sh_backward` for one channel of Gaussian g: its coefficients' gradients written
    into ``grad_shN``, the unit direction's gradient (gdx, gdy, gdz) carried on."""
    xx, yy, zz, xy, yz, xz = dx * dx, dy * dy, dz * dz, dx * dy, dy * dz, dx * dz
    grad_shN[g, 3, channel] = SH_C2[0] * xy * grad
    grad_shN[g, 4, channel] = SH_C2[1] * yz * grad
    grad_shN[g, 5, channel] = SH_C2[2] * (2.0 * zz - xx - yy) * grad
    grad_shN[g, 6, channel] = SH_C2[3] * xz * grad
    grad_shN[g, 7, channel] = SH_C2[4] * (xx - yy) * grad
    k = SH_C2[0] * grad * shN[g, 3, channel]
    gdx += k * dy
    gdy += k * dx
    k = SH_C2[1] * grad * shN[g, 4, channel]
    gdy += k * dz
    gdz += k * dy
    k = SH_C2[2] * grad * shN[g, 5, channel]
    gdx -= 2.0 * dx * k
    gdy -= 2.0 * dy * k
    gdz += 4.0 * dz * k
    k = SH_C2[3] * grad * shN[g, 6, channel]
    gdx += k * dz
    gdz += k * dx
    k = SH_C2[4] * grad * shN[g, 7, channel]
    gdx += 2.0 * dx * k
    gdy -= 2.0 * dy * k
    return gdx, gdy, gdz


@numba.njit(inline="always", error_model="numpy")
def _band3_backward(shN, g, channel, grad, dx, dy, dz, gdx, gdy, gdz, grad_shN):
    """Band 3's part of :func:`sh_backward`, as :func:`_band2_backward`."""
    xx, yy, zz, xy, yz, xz = dx * dx, dy * dy, dz * dz, dx * dy, dy * dz, dx * dz
    grad_shN[g, 8, channel] = SH_C3[0] * dy * (3.0 * xx - yy) * grad
    grad_shN[g, 9, channel] = SH_C3[1] * xy * dz * grad
    grad_shN[g, 10, channel] = SH_C3[2] * dy * (4.0 * zz - xx - yy) * grad
    grad_shN[g, 11, channel] = SH_C3[3] * dz * (2.0 * zz - 3.0 * xx - 3.0 * yy) * grad
    grad_shN[g, 12, channel] = SH_C3[4] * dx * (4.0 * zz - xx - yy) * grad
    grad_shN[g, 13, channel] = SH_C3[5] * dz * (xx - yy) * grad
    grad_shN[g, 14, channel] = SH_C3[6] * dx * (xx - 3.0 * yy) * grad
    k = SH_C3[0] * grad * shN[g, 8, channel]
    gdx += 6.0 * xy * k
    gdy += 3.0 * (xx - yy) * k
    k = SH_C3[1] * grad * shN[g, 9, channel]
    gdx += yz * k
    gdy += xz * k
    gdz += xy * k
    k = SH_C3[2] * grad * shN[g, 10, channel]
    gdx -= 2.0 * xy * k
    gdy += (4.0 * zz - xx - 3.0 * yy) * k
    gdz += 8.0 * yz * k
    k = SH_C3[3] * grad * shN[g, 11, channel]
    gdx -= 6.0 * xz * k
    gdy -= 6.0 * yz * k
    gdz += (6.0 * zz - 3.0 * xx - 3.0 * yy) * k
    k = SH_C3[4] * grad * shN[g, 12, channel]
    gdx += (4.0 * zz - 3.0 * xx - yy) * k
    gdy -= 2.0 * xy * k
    gdz += 8.0 * xz * k
    k = SH_C3[5] * grad * shN[g, 13, channel]
    gdx += 2.0 * xz * k
    gdy -= 2.0 * yz * k
    gdz += (xx - yy) * k
    k = SH_C3[6] * grad * shN[g, 14, channel]
    gdx += 3.0 * (xx - yy) * k
    gdy -= 6.0 * xy * k
    return gdx, gdy, gdz


@numba.njit(inline="always", error_model="numpy")
def sh_backward(degree, sh0, shN, g, m, grad_colours, dx, dy, dz, grad_sh0, grad_shN):
    """The gradients of :func:`sh_colour` for Gaussian g (row m of ``grad_colours`` (M, 3)) seen along the unit
    direction (dx, dy, dz): its coefficients' written into ``grad_sh0`` (N, 1, 3) and ``grad_shN`` (N, K - 1, 3),
    the direction's (gdx, gdy, gdz) returned."""
    gdx, gdy, gdz = 0.0, 0.0, 0.0
    for channel in range(3):
        grad = np.float64(grad_colours[m, channel])
        if sh_colour(degree, sh0, shN, g, dx, dy, dz, channel) <= 0.0:  # clamped at 0: no gradient
            grad = 0.0
        grad_sh0[g, 0, channel] = SH_C0 * grad
        if degree > 0:
            grad_shN[g, 0, channel] = -SH_C1 * dy * grad
            grad_shN[g, 1, channel] = SH_C1 * dz * grad
            grad_shN[g, 2, channel] = -SH_C1 * dx * grad
            gdy -= SH_C1 * grad * shN[g, 0, channel]
            gdz += SH_C1 * grad * shN[g, 1, channel]
            gdx -= SH_C1 * grad * shN[g, 2, channel]
        if degree > 1:
            gdx, gdy, gdz = _band2_backward(shN, g, channel, grad, dx, dy, dz, gdx, gdy, gdz, grad_shN)
        if degree > 2:
            gdx, gdy, gdz = _band3_backward(shN, g, channel, grad, dx, dy, dz, gdx, gdy, gdz, grad_shN)
    return gdx, gdy, gdz
