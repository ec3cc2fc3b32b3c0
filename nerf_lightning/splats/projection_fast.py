"""Projection and view-dependent colour in one numba loop: the CPU fast path for drawing a view without gradients
(``nerf-render``, ``nerf-eval``, the viewer, validation), beside the readable reference it is held equal to,
:func:`~nerf_lightning.splats.projection.project` then :func:`~nerf_lightning.splats.sh.spherical_harmonics`.

Why: once the tile rasteriser composites a small view in a few milliseconds, a frame's time goes into the
per-Gaussian tensor operations before it: a dozen (N, 3, 3) products, gathers and stacks, each a pass over memory
for every Gaussian. Here each Gaussian is taken once, its footprint and colour computed in registers, Gaussians in
parallel; the survivors are then gathered in index order, as the reference's ``nonzero`` keeps them, so that the
rasteriser sees the same footprints in the same order and draws the same image.

Training keeps the PyTorch reference: its autograd carries the gradients to every Gaussian parameter.
"""

from __future__ import annotations

import math

import numba
import numpy as np
import torch

from nerf_lightning.splats.projection import LOW_PASS, MAX_SIGMAS, MIN_ALPHA, NEAR_PLANE, Projection
from nerf_lightning.splats.sh import SH_C0, SH_C1, SH_C2, SH_C3, coefficients_for


@numba.njit(inline="always")
def _sh_colour(degree, sh0, shN, g, x, y, z, channel):
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


@numba.njit(parallel=True, cache=True, error_model="numpy")
def project_and_shade_loop(means, quats, log_scales, opacities, sh0, shN, degree, camera, height, width, antialiased,
                           footprints, colours, seen):
    """Every Gaussian at once, in parallel. ``camera`` (19,): the world-to-camera rotation (9, row-major),
    translation (3), fx, fy, cx, cy and the camera's centre in the world (3). Written, for Gaussian g: ``footprints[g]`` (9,) = means2d (2), conic (3), opacity,
    depth, extents (2), ``colours[g]`` (3,), ``seen[g]`` whether it is drawn."""
    r00, r01, r02, r10, r11, r12, r20, r21, r22 = (camera[0], camera[1], camera[2], camera[3], camera[4], camera[5],
                                                   camera[6], camera[7], camera[8])
    t0, t1, t2 = camera[9], camera[10], camera[11]
    fx, fy, cx, cy = camera[12], camera[13], camera[14], camera[15]
    ox, oy, oz = camera[16], camera[17], camera[18]
    limit_x0, limit_x1 = -(cx / fx + 0.3 * 0.5 * width / fx), (width - cx) / fx + 0.3 * 0.5 * width / fx
    limit_y0, limit_y1 = -(cy / fy + 0.3 * 0.5 * height / fy), (height - cy) / fy + 0.3 * 0.5 * height / fy
    for g in numba.prange(means.shape[0]):
        seen[g] = False
        mx, my, mz = means[g, 0], means[g, 1], means[g, 2]
        x = r00 * mx + r01 * my + r02 * mz + t0
        y = r10 * mx + r11 * my + r12 * mz + t1
        z = r20 * mx + r21 * my + r22 * mz + t2
        if not z > NEAR_PLANE:
            continue
        # the covariance R S S^T R^T from the normalised quaternion (w, x, y, z)
        qw, qx, qy, qz = quats[g, 0], quats[g, 1], quats[g, 2], quats[g, 3]
        norm = max(math.sqrt(qw * qw + qx * qx + qy * qy + qz * qz), 1e-12)
        qw, qx, qy, qz = qw / norm, qx / norm, qy / norm, qz / norm
        s0, s1, s2 = math.exp(log_scales[g, 0]), math.exp(log_scales[g, 1]), math.exp(log_scales[g, 2])
        m00, m01, m02 = (1.0 - 2.0 * (qy * qy + qz * qz)) * s0, 2.0 * (qx * qy - qw * qz) * s1, 2.0 * (qx * qz + qw * qy) * s2
        m10, m11, m12 = 2.0 * (qx * qy + qw * qz) * s0, (1.0 - 2.0 * (qx * qx + qz * qz)) * s1, 2.0 * (qy * qz - qw * qx) * s2
        m20, m21, m22 = 2.0 * (qx * qz - qw * qy) * s0, 2.0 * (qy * qz + qw * qx) * s1, (1.0 - 2.0 * (qx * qx + qy * qy)) * s2
        # W (R S): the Gaussian's axes in the camera; its covariance there is (W R S)(W R S)^T
        a00 = r00 * m00 + r01 * m10 + r02 * m20
        a01 = r00 * m01 + r01 * m11 + r02 * m21
        a02 = r00 * m02 + r01 * m12 + r02 * m22
        a10 = r10 * m00 + r11 * m10 + r12 * m20
        a11 = r10 * m01 + r11 * m11 + r12 * m21
        a12 = r10 * m02 + r11 * m12 + r12 * m22
        a20 = r20 * m00 + r21 * m10 + r22 * m20
        a21 = r20 * m01 + r21 * m11 + r22 * m21
        a22 = r20 * m02 + r21 * m12 + r22 * m22
        tx = z * min(max(x / z, limit_x0), limit_x1)
        ty = z * min(max(y / z, limit_y0), limit_y1)
        # J (W R S): the footprint's covariance is its Gram matrix
        j00, j02, j11, j12 = fx / z, -fx * tx / (z * z), fy / z, -fy * ty / (z * z)
        u0, u1, u2 = j00 * a00 + j02 * a20, j00 * a01 + j02 * a21, j00 * a02 + j02 * a22
        v0, v1, v2 = j11 * a10 + j12 * a20, j11 * a11 + j12 * a21, j11 * a12 + j12 * a22
        f00, f01, f11 = u0 * u0 + u1 * u1 + u2 * u2, u0 * v0 + u1 * v1 + u2 * v2, v0 * v0 + v1 * v1 + v2 * v2
        a, b, c = f00 + LOW_PASS, f01, f11 + LOW_PASS
        determinant = a * c - b * b
        alpha = opacities[g]
        if antialiased:
            alpha = alpha * math.sqrt(max((f00 * f11 - b * b) / determinant, 1e-10))
        u, v = fx * x / z + cx, fy * y / z + cy
        sigmas = min(math.sqrt(2.0 * math.log(max(alpha / MIN_ALPHA, 1.0))), MAX_SIGMAS)
        extent_u, extent_v = sigmas * math.sqrt(max(a, 0.0)), sigmas * math.sqrt(max(c, 0.0))
        if not (determinant > 0.0 and sigmas > 0.0 and u + extent_u >= 0.5 and u - extent_u <= width - 0.5
                and v + extent_v >= 0.5 and v - extent_v <= height - 0.5):
            continue
        seen[g] = True
        footprints[g, 0], footprints[g, 1] = u, v
        footprints[g, 2], footprints[g, 3], footprints[g, 4] = c / determinant, -b / determinant, a / determinant
        footprints[g, 5], footprints[g, 6] = alpha, z
        footprints[g, 7], footprints[g, 8] = extent_u, extent_v
        # the colour seen from the camera's centre
        dx, dy, dz = mx - ox, my - oy, mz - oz
        length = max(math.sqrt(dx * dx + dy * dy + dz * dz), 1e-12)
        dx, dy, dz = dx / length, dy / length, dz / length
        for channel in range(3):
            colours[g, channel] = _sh_colour(degree, sh0, shN, g, dx, dy, dz, channel)


def project_and_shade(means: torch.Tensor, quats: torch.Tensor, log_scales: torch.Tensor, opacities: torch.Tensor,
                      sh0: torch.Tensor, shN: torch.Tensor, degree: int, K: torch.Tensor, c2w: torch.Tensor, height: int,
                      width: int, antialiased: bool = False) -> tuple[Projection, torch.Tensor]:
    """N Gaussians (means (N, 3), quats (N, 4), log_scales (N, 3), opacities (N,) in (0, 1), sh0 (N, 1, 3), shN
    (N, K - 1, 3)) seen by a pinhole camera (K (3, 3), OpenCV c2w (4, 4)) -> the :class:`Projection` of those drawn
    and their (M, 3) colours of SH ``degree``, as ``project`` and ``spherical_harmonics`` give them; CPU tensors,
    no gradients."""
    if not 0 <= degree <= 3 or shN.shape[1] < coefficients_for(degree) - 1:
        raise ValueError(f"project_and_shade of SH degree {degree} needs 0 <= degree <= 3 and shN (N, >= "
                         f"{coefficients_for(degree) - 1}, 3), got {tuple(shN.shape)}")
    dtype = means.dtype
    c2w = c2w.detach().to(torch.float64)
    w2c = torch.linalg.inv(c2w)
    K = K.detach().to(torch.float64)
    camera = torch.cat([w2c[:3, :3].reshape(-1), w2c[:3, 3], K[0, 0:1], K[1, 1:2], K[0, 2:3], K[1, 2:3], c2w[:3, 3]])
    arrays = [x.detach().contiguous().numpy() for x in (means, quats, log_scales, opacities, sh0, shN)]
    if arrays[5].shape[1] == 0:  # numba needs an array it may index (never read at degree 0)
        arrays[5] = np.zeros((len(arrays[0]), 1, 3), arrays[0].dtype)
    n = len(arrays[0])
    footprints = np.empty((n, 9), arrays[0].dtype)
    colours = np.empty((n, 3), arrays[0].dtype)
    seen = np.empty(n, np.bool_)
    project_and_shade_loop(*arrays, degree, camera.to(dtype).numpy(), height, width, antialiased, footprints, colours, seen)
    ids = np.flatnonzero(seen)
    kept = torch.from_numpy(footprints[ids])
    projection = Projection(torch.from_numpy(ids), kept[:, 0:2], kept[:, 2:5], kept[:, 5], kept[:, 6], kept[:, 7:9])
    return projection, torch.from_numpy(colours[ids])
