"""Projection and view-dependent colour in one numba loop, forward and backward: the CPU fast path beside the
readable reference it is held equal to, :func:`~nerf_lightning.splats.projection.project` then
:func:`~nerf_lightning.splats.sh.spherical_harmonics`.

Why: once the tile rasteriser composites a view in a few milliseconds, a step's time goes into the per-Gaussian
tensor operations around it: a dozen (N, 3, 3) products, gathers and stacks, and autograd's as many again backward,
each a pass over memory for every Gaussian. Here each Gaussian is taken once, its footprint and colour computed in
registers, Gaussians in parallel; the survivors are then gathered in index order, as the reference's ``nonzero``
keeps them, so that the rasteriser sees the same footprints in the same order and draws the same image.

The backward pass (:func:`project_and_shade_backward_loop`) recomputes each drawn Gaussian's footprint and takes
the chain rule back through the conic, the EWA Jacobian, the rotation and scales, the normalised quaternion, the
mean and the SH colour's direction, as autograd does through the reference (the tests hold the gradients equal).
Each Gaussian's gradient is written to its own row by one thread: no sums race, so the same input gives the same
gradients bit for bit.

Where the camera itself is learned (camera refinement), the reference draws: this path takes no camera gradient.
"""

from __future__ import annotations

import math

import numba
import numpy as np
import torch

from nerf_lightning.splats.projection import LOW_PASS, MAX_SIGMAS, MIN_ALPHA, NEAR_PLANE, Projection
from nerf_lightning.splats.sh import coefficients_for
from nerf_lightning.splats.sh_fast import sh_backward, sh_colour



@numba.njit(inline="always", error_model="numpy")
def _unit_rotation(pw, px, py, pz):
    """The quaternion (w, x, y, z) normalised, its norm, and its rotation matrix's nine entries (row-major)."""
    pw, px, py, pz = np.float64(pw), np.float64(px), np.float64(py), np.float64(pz)
    norm = max(math.sqrt(pw * pw + px * px + py * py + pz * pz), 1e-12)
    qw, qx, qy, qz = pw / norm, px / norm, py / norm, pz / norm
    return (qw, qx, qy, qz, norm,
            1.0 - 2.0 * (qy * qy + qz * qz), 2.0 * (qx * qy - qw * qz), 2.0 * (qx * qz + qw * qy),
            2.0 * (qx * qy + qw * qz), 1.0 - 2.0 * (qx * qx + qz * qz), 2.0 * (qy * qz - qw * qx),
            2.0 * (qx * qz - qw * qy), 2.0 * (qy * qz + qw * qx), 1.0 - 2.0 * (qx * qx + qy * qy))


@numba.njit(inline="always", error_model="numpy")
def _product(r00, r01, r02, r10, r11, r12, r20, r21, r22, m00, m01, m02, m10, m11, m12, m20, m21, m22):
    """The 3x3 product R M, row-major."""
    return (r00 * m00 + r01 * m10 + r02 * m20, r00 * m01 + r01 * m11 + r02 * m21, r00 * m02 + r01 * m12 + r02 * m22,
            r10 * m00 + r11 * m10 + r12 * m20, r10 * m01 + r11 * m11 + r12 * m21, r10 * m02 + r11 * m12 + r12 * m22,
            r20 * m00 + r21 * m10 + r22 * m20, r20 * m01 + r21 * m11 + r22 * m21, r20 * m02 + r21 * m12 + r22 * m22)


@numba.njit(inline="always", error_model="numpy")
def _ewa_rows(x, y, z, fx, fy, limit_x0, limit_x1, limit_y0, limit_y1,
              a00, a01, a02, a10, a11, a12, a20, a21, a22):
    """The EWA Jacobian J at the camera-space mean (x, y, z), its x / z and y / z clamped to the limits (as the
    reference clamps them), and the footprint's axes U = J A (its rows u, v; the footprint's covariance is U U^T)
    for the Gaussian's axes A in the camera. Returns x / z, y / z, both clamped, tx, ty, J's four entries, u, v."""
    ratio_x, ratio_y = x / z, y / z
    clamped_x, clamped_y = min(max(ratio_x, limit_x0), limit_x1), min(max(ratio_y, limit_y0), limit_y1)
    tx, ty = z * clamped_x, z * clamped_y
    j00, j02, j11, j12 = fx / z, -fx * tx / (z * z), fy / z, -fy * ty / (z * z)
    return (ratio_x, ratio_y, clamped_x, clamped_y, tx, ty, j00, j02, j11, j12,
            j00 * a00 + j02 * a20, j00 * a01 + j02 * a21, j00 * a02 + j02 * a22,
            j11 * a10 + j12 * a20, j11 * a11 + j12 * a21, j11 * a12 + j12 * a22)


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
        (_, _, _, _, _, q00, q01, q02, q10, q11, q12, q20, q21, q22) = _unit_rotation(quats[g, 0], quats[g, 1], quats[g, 2], quats[g, 3])
        s0, s1, s2 = math.exp(log_scales[g, 0]), math.exp(log_scales[g, 1]), math.exp(log_scales[g, 2])
        # W (R S): the Gaussian's axes in the camera; its covariance there is (W R S)(W R S)^T
        a00, a01, a02, a10, a11, a12, a20, a21, a22 = _product(r00, r01, r02, r10, r11, r12, r20, r21, r22,
                                                               q00 * s0, q01 * s1, q02 * s2, q10 * s0, q11 * s1,
                                                               q12 * s2, q20 * s0, q21 * s1, q22 * s2)
        # J (W R S): the footprint's covariance is its Gram matrix
        (_, _, _, _, _, _, _, _, _, _, u0, u1, u2, v0, v1, v2) = _ewa_rows(x, y, z, fx, fy, limit_x0, limit_x1, limit_y0, limit_y1,
                                                                        a00, a01, a02, a10, a11, a12, a20, a21, a22)
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
            colours[g, channel] = sh_colour(degree, sh0, shN, g, dx, dy, dz, channel)


@numba.njit(inline="always", error_model="numpy")
def _covariance_backward(grad_footprints, m, opacity, antialiased, a, b, c, f00, f11, determinant):
    """The loss's gradients of footprint m's conic (c, -b, a) / det and opacity (``grad_footprints`` (M, 7)) back to
    its covariance F = U U^T, through F + 0.3 I and with ``antialiased`` the opacity's compensation: d F00, d F11,
    d F01 (b) and the Gaussian's ``opacity``'s gradient."""
    inverse = 1.0 / determinant
    grad_det = -inverse * inverse * (grad_footprints[m, 2] * c - grad_footprints[m, 3] * b + grad_footprints[m, 4] * a)
    grad_a, grad_b, grad_c = grad_footprints[m, 4] * inverse, -grad_footprints[m, 3] * inverse, grad_footprints[m, 2] * inverse
    grad_f00, grad_f11 = 0.0, 0.0
    grad_alpha = np.float64(grad_footprints[m, 5])
    if antialiased:  # alpha = o sqrt(max(det(F) / det(F + 0.3 I), 1e-10))
        unfiltered = f00 * f11 - b * b
        ratio = unfiltered / determinant
        if ratio >= 1e-10:
            compensation = math.sqrt(ratio)
            grad_ratio = grad_alpha * opacity * 0.5 / compensation
            grad_unfiltered = grad_ratio / determinant
            grad_det -= grad_ratio * ratio / determinant
            grad_f00 += grad_unfiltered * f11
            grad_f11 += grad_unfiltered * f00
            grad_b -= 2.0 * b * grad_unfiltered
        else:
            compensation = math.sqrt(1e-10)
        grad_opacity = grad_alpha * compensation
    else:
        grad_opacity = grad_alpha
    grad_a += grad_det * c
    grad_c += grad_det * a
    grad_b -= 2.0 * b * grad_det
    grad_f00 += grad_a
    grad_f11 += grad_c
    return grad_f00, grad_f11, grad_b, grad_opacity


@numba.njit(inline="always", error_model="numpy")
def _scale_rotation_backward(gm00, gm01, gm02, gm10, gm11, gm12, gm20, gm21, gm22, q00, q01, q02, q10, q11, q12, q20, q21,
                             q22, s0, s1, s2, qw, qx, qy, qz, norm, grad_log_scales, grad_quats):
    """The gradient of M = R(q) diag(s) (gm, row-major) back to the log scales and to the quaternion before its
    normalisation (norm |q|, unit (qw, qx, qy, qz), rotation q00..q22), written into one Gaussian's rows
    ``grad_log_scales`` (3,) and ``grad_quats`` (4,)."""
    # M = R(q) diag(s): the log scales and the rotation
    grad_log_scales[0] = (gm00 * q00 + gm10 * q10 + gm20 * q20) * s0
    grad_log_scales[1] = (gm01 * q01 + gm11 * q11 + gm21 * q21) * s1
    grad_log_scales[2] = (gm02 * q02 + gm12 * q12 + gm22 * q22) * s2
    g00, g01, g02 = gm00 * s0, gm01 * s1, gm02 * s2
    g10, g11, g12 = gm10 * s0, gm11 * s1, gm12 * s2
    g20, g21, g22 = gm20 * s0, gm21 * s1, gm22 * s2
    gw = 2.0 * (-qz * g01 + qy * g02 + qz * g10 - qx * g12 - qy * g20 + qx * g21)
    gx = 2.0 * (qy * g01 + qz * g02 + qy * g10 - 2.0 * qx * g11 - qw * g12 + qz * g20 + qw * g21 - 2.0 * qx * g22)
    gy = 2.0 * (-2.0 * qy * g00 + qx * g01 + qw * g02 + qx * g10 + qz * g12 - qw * g20 + qz * g21 - 2.0 * qy * g22)
    gz = 2.0 * (-2.0 * qz * g00 - qw * g01 + qx * g02 + qw * g10 - 2.0 * qz * g11 + qy * g12 + qx * g20 + qy * g21)
    # the quaternion's normalisation q / |q|
    along = qw * gw + qx * gx + qy * gy + qz * gz
    grad_quats[0] = (gw - qw * along) / norm
    grad_quats[1] = (gx - qx * along) / norm
    grad_quats[2] = (gy - qy * along) / norm
    grad_quats[3] = (gz - qz * along) / norm


@numba.njit(inline="always", error_model="numpy")
def _axes_backward(grad_f00, grad_f11, grad_b, u0, u1, u2, v0, v1, v2, a00, a01, a02, a10, a11, a12, a20, a21, a22,
                   j00, j02, j11, j12, camera):
    """The gradient of the footprint's covariance F = U U^T (d F00, d F11, d F01 = b), U = J A (rows u, v), A = W M,
    back to the EWA Jacobian J's four entries and to M = R(q) diag(s) (row-major), for W the camera's rotation (the
    first nine of ``camera``, row-major). Fewer than 31 arguments: CPython passes more as a tuple, which numba cannot
    inline."""
    r00, r01, r02, r10, r11, r12, r20, r21, r22 = (camera[0], camera[1], camera[2], camera[3], camera[4], camera[5],
                                                   camera[6], camera[7], camera[8])
    gu0, gu1, gu2 = 2.0 * grad_f00 * u0 + grad_b * v0, 2.0 * grad_f00 * u1 + grad_b * v1, 2.0 * grad_f00 * u2 + grad_b * v2
    gv0, gv1, gv2 = 2.0 * grad_f11 * v0 + grad_b * u0, 2.0 * grad_f11 * v1 + grad_b * u1, 2.0 * grad_f11 * v2 + grad_b * u2
    grad_j00 = gu0 * a00 + gu1 * a01 + gu2 * a02
    grad_j02 = gu0 * a20 + gu1 * a21 + gu2 * a22
    grad_j11 = gv0 * a10 + gv1 * a11 + gv2 * a12
    grad_j12 = gv0 * a20 + gv1 * a21 + gv2 * a22
    ga00, ga01, ga02 = j00 * gu0, j00 * gu1, j00 * gu2
    ga10, ga11, ga12 = j11 * gv0, j11 * gv1, j11 * gv2
    ga20, ga21, ga22 = j02 * gu0 + j12 * gv0, j02 * gu1 + j12 * gv1, j02 * gu2 + j12 * gv2
    # A = W M: d M = W^T d A
    gm00, gm01, gm02, gm10, gm11, gm12, gm20, gm21, gm22 = _product(r00, r10, r20, r01, r11, r21, r02, r12, r22,
                                                                    ga00, ga01, ga02, ga10, ga11, ga12, ga20, ga21, ga22)
    return grad_j00, grad_j02, grad_j11, grad_j12, gm00, gm01, gm02, gm10, gm11, gm12, gm20, gm21, gm22


@numba.njit(parallel=True, cache=True, error_model="numpy")
def project_and_shade_backward_loop(means, quats, log_scales, opacities, sh0, shN, degree, camera, height, width,
                                    antialiased, ids, grad_footprints, grad_colours, grad_means, grad_quats,
                                    grad_log_scales, grad_opacities, grad_sh0, grad_shN):
    """The gradients of :func:`project_and_shade_loop` for the drawn Gaussians ``ids`` (M,): ``grad_footprints``
    (M, 7) the loss's gradients of means2d (2), conic (3), opacity and depth, ``grad_colours`` (M, 3). Written, for
    Gaussian ``ids[m]``, its rows of ``grad_means`` (N, 3), ``grad_quats`` (N, 4), ``grad_log_scales`` (N, 3),
    ``grad_opacities`` (N,), ``grad_sh0`` (N, 1, 3) and ``grad_shN`` (N, K - 1, 3) (the other rows are left as
    they are)."""
    r00, r01, r02, r10, r11, r12, r20, r21, r22 = (camera[0], camera[1], camera[2], camera[3], camera[4], camera[5],
                                                   camera[6], camera[7], camera[8])
    t0, t1, t2 = camera[9], camera[10], camera[11]
    fx, fy, cx, cy = camera[12], camera[13], camera[14], camera[15]
    ox, oy, oz = camera[16], camera[17], camera[18]
    limit_x0, limit_x1 = -(cx / fx + 0.3 * 0.5 * width / fx), (width - cx) / fx + 0.3 * 0.5 * width / fx
    limit_y0, limit_y1 = -(cy / fy + 0.3 * 0.5 * height / fy), (height - cy) / fy + 0.3 * 0.5 * height / fy
    for m in numba.prange(ids.shape[0]):
        g = ids[m]
        # -- the forward pass again, as project_and_shade_loop takes it
        mx, my, mz = np.float64(means[g, 0]), np.float64(means[g, 1]), np.float64(means[g, 2])
        x = r00 * mx + r01 * my + r02 * mz + t0
        y = r10 * mx + r11 * my + r12 * mz + t1
        z = r20 * mx + r21 * my + r22 * mz + t2
        (qw, qx, qy, qz, norm, q00, q01, q02, q10, q11, q12, q20, q21, q22) = _unit_rotation(quats[g, 0], quats[g, 1], quats[g, 2],
                                                                                              quats[g, 3])
        s0, s1, s2 = math.exp(log_scales[g, 0]), math.exp(log_scales[g, 1]), math.exp(log_scales[g, 2])
        a00, a01, a02, a10, a11, a12, a20, a21, a22 = _product(r00, r01, r02, r10, r11, r12, r20, r21, r22,
                                                               q00 * s0, q01 * s1, q02 * s2, q10 * s0, q11 * s1,
                                                               q12 * s2, q20 * s0, q21 * s1, q22 * s2)
        (ratio_x, ratio_y, clamped_x, clamped_y, tx, ty, j00, j02, j11, j12,
         u0, u1, u2, v0, v1, v2) = _ewa_rows(x, y, z, fx, fy, limit_x0, limit_x1, limit_y0, limit_y1,
                                              a00, a01, a02, a10, a11, a12, a20, a21, a22)
        f00, f01, f11 = u0 * u0 + u1 * u1 + u2 * u2, u0 * v0 + u1 * v1 + u2 * v2, v0 * v0 + v1 * v1 + v2 * v2
        a, b, c = f00 + LOW_PASS, f01, f11 + LOW_PASS
        determinant = a * c - b * b
        # -- the conic (c, -b, a) / det and the opacity, back to the footprint's covariance
        grad_u, grad_v = np.float64(grad_footprints[m, 0]), np.float64(grad_footprints[m, 1])
        grad_f00, grad_f11, grad_b, grad_opacity = _covariance_backward(grad_footprints, m, opacities[g], antialiased, a, b,
                                                                        c, f00, f11, determinant)
        grad_opacities[g] = grad_opacity
        # -- F = U U^T with U = J A (rows u, v), A = W R S
        (grad_j00, grad_j02, grad_j11, grad_j12,
         gm00, gm01, gm02, gm10, gm11, gm12, gm20, gm21, gm22) = _axes_backward(grad_f00, grad_f11, grad_b, u0, u1, u2, v0, v1, v2,
                                                                               a00, a01, a02, a10, a11, a12, a20, a21, a22,
                                                                               j00, j02, j11, j12, camera)
        _scale_rotation_backward(gm00, gm01, gm02, gm10, gm11, gm12, gm20, gm21, gm22, q00, q01, q02, q10, q11, q12,
                                 q20, q21, q22, s0, s1, s2, qw, qx, qy, qz, norm, grad_log_scales[g], grad_quats[g])
        # -- the mean in the camera: means2d, depth and J (at x / z and y / z clamped)
        z2 = z * z
        grad_x, grad_y = grad_u * fx / z, grad_v * fy / z
        grad_z = -grad_u * fx * x / z2 - grad_v * fy * y / z2 + grad_footprints[m, 6]
        grad_z -= fx / z2 * grad_j00 + fy / z2 * grad_j11
        grad_z += 2.0 * (fx * tx * grad_j02 + fy * ty * grad_j12) / (z2 * z)
        grad_tx, grad_ty = -fx / z2 * grad_j02, -fy / z2 * grad_j12
        if limit_x0 <= ratio_x <= limit_x1:  # t = z (x / z): d t / dx = 1, d t / dz = 0
            grad_x += grad_tx
        else:  # t = z limit
            grad_z += grad_tx * clamped_x
        if limit_y0 <= ratio_y <= limit_y1:
            grad_y += grad_ty
        else:
            grad_z += grad_ty * clamped_y
        gmx = r00 * grad_x + r10 * grad_y + r20 * grad_z
        gmy = r01 * grad_x + r11 * grad_y + r21 * grad_z
        gmz = r02 * grad_x + r12 * grad_y + r22 * grad_z
        # -- the colour: the coefficients, and the direction from the camera's centre (which moves with the mean)
        dx, dy, dz = mx - ox, my - oy, mz - oz
        length = max(math.sqrt(dx * dx + dy * dy + dz * dz), 1e-12)
        dx, dy, dz = dx / length, dy / length, dz / length
        gdx, gdy, gdz = sh_backward(degree, sh0, shN, g, m, grad_colours, dx, dy, dz, grad_sh0, grad_shN)
        if degree > 0:  # the direction's normalisation d / |d|
            along = dx * gdx + dy * gdy + dz * gdz
            gmx += (gdx - dx * along) / length
            gmy += (gdy - dy * along) / length
            gmz += (gdz - dz * along) / length
        grad_means[g, 0], grad_means[g, 1], grad_means[g, 2] = gmx, gmy, gmz


@numba.njit(cache=True)
def keep_seen(seen, footprints, colours):
    """The drawn Gaussians' rows (``seen`` (N,) bool) of ``footprints`` (N, 9) and ``colours`` (N, 3), in index
    order, as separate contiguous arrays: means2d (M, 2), conics (M, 3), opacities (M,), depths (M,), colours (M, 3),
    extents (M, 2) and their ids (M,) int64. One pass, where numpy's gather and then a copy of each column slice
    would take several over the rows."""
    ids = np.flatnonzero(seen)
    m, dtype = ids.shape[0], footprints.dtype
    means2d, conics, extents = np.empty((m, 2), dtype), np.empty((m, 3), dtype), np.empty((m, 2), dtype)
    opacities, depths, kept_colours = np.empty(m, dtype), np.empty(m, dtype), np.empty((m, 3), dtype)
    for i in range(m):
        g = ids[i]
        means2d[i, 0], means2d[i, 1] = footprints[g, 0], footprints[g, 1]
        conics[i, 0], conics[i, 1], conics[i, 2] = footprints[g, 2], footprints[g, 3], footprints[g, 4]
        opacities[i], depths[i] = footprints[g, 5], footprints[g, 6]
        extents[i, 0], extents[i, 1] = footprints[g, 7], footprints[g, 8]
        kept_colours[i, 0], kept_colours[i, 1], kept_colours[i, 2] = colours[g, 0], colours[g, 1], colours[g, 2]
    return means2d, conics, opacities, depths, kept_colours, extents, ids.astype(np.int64)


class ProjectAndShade(torch.autograd.Function):
    """:func:`project_and_shade_loop` and its gradients as one autograd step: N Gaussians' means (N, 3), quats (N, 4),
    log_scales (N, 3), opacities (N,), sh0 (N, 1, 3), shN (N, K - 1, 3) -> for the M drawn, means2d (M, 2), conics
    (M, 3), opacities (M,), depths (M,), colours (M, 3), and without gradients extents (M, 2) and ids (M,) long."""

    @staticmethod
    def forward(ctx, means, quats, log_scales, opacities, sh0, shN, degree: int, camera: np.ndarray, height: int,
                width: int, antialiased: bool):
        arrays = [x.detach().contiguous().numpy() for x in (means, quats, log_scales, opacities, sh0, shN)]
        if arrays[5].shape[1] == 0:  # numba needs an array it may index (never read at degree 0)
            arrays[5] = np.zeros((len(arrays[0]), 1, 3), arrays[0].dtype)
        n = len(arrays[0])
        # from torch, not numpy: see the backward's gradients
        footprints = torch.empty((n, 9), dtype=means.dtype).numpy()
        colours = torch.empty((n, 3), dtype=means.dtype).numpy()
        seen = np.empty(n, np.bool_)
        project_and_shade_loop(*arrays, degree, camera, height, width, antialiased, footprints, colours, seen)
        outputs = keep_seen(seen, footprints, colours)
        ids = outputs[-1]
        ctx.saved = (arrays, means.dtype, degree, camera, height, width, antialiased, ids, shN.shape)
        outputs = tuple(torch.from_numpy(value) for value in outputs)
        ctx.mark_non_differentiable(outputs[5], outputs[6])
        return outputs

    @staticmethod
    def backward(ctx, grad_means2d, grad_conics, grad_opacities, grad_depths, grad_colours, _extents, _ids):
        arrays, torch_dtype, degree, camera, height, width, antialiased, ids, shN_shape = ctx.saved
        m, dtype = len(ids), arrays[0].dtype
        parts = [(grad_means2d, 2), (grad_conics, 3), (grad_opacities, 0), (grad_depths, 0)]
        grad_footprints = np.concatenate([np.zeros((m, max(size, 1)), dtype) if grad is None else
                                          grad.detach().reshape(m, max(size, 1)).numpy().astype(dtype, copy=False)
                                          for grad, size in parts], axis=1)
        grad_colours = np.zeros((m, 3), dtype) if grad_colours is None else \
            grad_colours.detach().contiguous().numpy().astype(dtype, copy=False)
        # computed in float64, rounded once as written. Allocated by torch, not numpy: numpy asks the kernel for huge
        # pages for large arrays, and where the kernel compacts memory to find them (transparent huge pages with
        # defrag=madvise) the loop's first writes into these Gaussian-sized arrays stall on it, every step
        # (one zero fill for all six, cut into views: one operator, not six)
        sizes = [array.size for array in arrays]
        flat = torch.zeros(sum(sizes), dtype=torch_dtype)
        grads = [part.view(array.shape) for part, array in zip(flat.split(sizes), arrays, strict=True)]
        project_and_shade_backward_loop(*arrays, degree, camera, height, width, antialiased, ids, grad_footprints,
                                        grad_colours, *(grad.numpy() for grad in grads))
        grads[5] = grads[5][:, : shN_shape[1]]  # shN without higher bands: its own empty shape back
        return (*grads, None, None, None, None, None)


def camera_array(K: torch.Tensor, c2w: torch.Tensor, dtype: torch.dtype) -> np.ndarray:
    """(19,) the loops' camera: world-to-camera rotation (row-major) and translation, fx, fy, cx, cy, the centre.
    Inverted in numpy's float64, not torch's: a training step makes no float64 tensor (Apple GPUs have none)."""
    c2w_array = c2w.detach().cpu().numpy().astype(np.float64)
    w2c = np.linalg.inv(c2w_array)
    K_array = K.detach().cpu().numpy().astype(np.float64)
    camera = np.concatenate([w2c[:3, :3].reshape(-1), w2c[:3, 3], [K_array[0, 0], K_array[1, 1], K_array[0, 2],
                                                                    K_array[1, 2]], c2w_array[:3, 3]])
    return camera.astype(torch.empty((), dtype=dtype).numpy().dtype)


def project_and_shade(means: torch.Tensor, quats: torch.Tensor, log_scales: torch.Tensor, opacities: torch.Tensor,
                      sh0: torch.Tensor, shN: torch.Tensor, degree: int, K: torch.Tensor, c2w: torch.Tensor, height: int,
                      width: int, antialiased: bool = False) -> tuple[Projection, torch.Tensor]:
    """N Gaussians (means (N, 3), quats (N, 4), log_scales (N, 3), opacities (N,) in (0, 1), sh0 (N, 1, 3), shN
    (N, K - 1, 3)) seen by a pinhole camera (K (3, 3), OpenCV c2w (4, 4)) -> the :class:`Projection` of those drawn
    and their (M, 3) colours of SH ``degree``, as ``project`` and ``spherical_harmonics`` give them; CPU tensors,
    differentiable in the six Gaussian tensors (not in the camera)."""
    if not 0 <= degree <= 3 or shN.shape[1] < coefficients_for(degree) - 1:
        raise ValueError(f"project_and_shade of SH degree {degree} needs 0 <= degree <= 3 and shN (N, >= "
                         f"{coefficients_for(degree) - 1}, 3), got {tuple(shN.shape)}")
    camera = camera_array(K, c2w, means.dtype)
    means2d, conics, alphas, depths, colours, extents, ids = ProjectAndShade.apply(
        means, quats, log_scales, opacities, sh0, shN, degree, camera, height, width, antialiased)
    return Projection(ids, means2d, conics, alphas, depths, extents), colours
