"""Projecting 3D Gaussians into a pinhole camera: EWA splatting (Zwicker et al. 2001), as 3D Gaussian splatting
(Kerbl et al. 2023) and gsplat do it.

A Gaussian has a mean mu (3,), a rotation q (a unit quaternion, w x y z) and scales s (3,); its covariance is
Sigma = R S S^T R^T with R = R(q) and S = diag(s). In a camera with world-to-camera rotation W and translation t,
its mean is p = W mu + t = (x, y, z) and its covariance W Sigma W^T. The perspective projection is not linear; EWA
replaces it by its Jacobian at p,

    J = [[fx / z, 0, -fx x / z^2],
         [0, fy / z, -fy y / z^2]],

so that the Gaussian's footprint on the image is the 2D Gaussian of mean (fx x / z + cx, fy y / z + cy) and
covariance J W Sigma W^T J^T + 0.3 I: the 0.3 px^2 is a low-pass filter, so that no splat is thinner than a pixel.
x / z and y / z are clamped a little beyond the image's edges before J is formed: a Gaussian far outside the view
would otherwise get a huge, unstable footprint. With ``antialiased`` (Mip-Splatting), the opacity is multiplied by
sqrt(det(cov) / det(cov + 0.3 I)), so that the low-pass filter does not make small Gaussians brighter.

Cameras are OpenCV's (x right, y down, looking down +z), pixel (i, j)'s centre at (j + 0.5, i + 0.5), as everywhere
in the project (:mod:`nerf_lightning.geometry.cameras`).
"""

from __future__ import annotations

import math
from typing import NamedTuple

import torch
from kornia.geometry.conversions import quaternion_to_rotation_matrix

# the low-pass filter added to every footprint's covariance, in px^2 (3DGS's and gsplat's)
LOW_PASS = 0.3
# Gaussians whose mean is nearer the camera than this (camera units) are not drawn (gsplat's near plane)
NEAR_PLANE = 0.01
# a footprint reaches at most this many standard deviations from its mean (3DGS's radius)
MAX_SIGMAS = 3.0
# the smallest opacity a pixel is given by a Gaussian (3DGS's and gsplat's 1/255): fainter pairs are skipped
MIN_ALPHA = 1.0 / 255.0
# the most opacity a footprint gives a pixel (3DGS's 0.99, gsplat's 0.999): never fully opaque, so that the backward
# pass can divide by 1 - alpha
MAX_ALPHA = 0.999
# a pixel whose transmittance would fall to this or below takes no more footprints (3DGS's early stop)
MIN_TRANSMITTANCE = 1e-4


def covariances(quats: torch.Tensor, log_scales: torch.Tensor) -> torch.Tensor:
    """(N, 4) quaternions (w, x, y, z; normalised here) and (N, 3) log scales -> (N, 3, 3) covariances R S S^T R^T."""
    rotations = quaternion_to_rotation_matrix(torch.nn.functional.normalize(quats, dim=-1))  # (N, 3, 3)
    halves = rotations * torch.exp(log_scales)[:, None, :]  # R S: column k scaled by s_k
    return halves @ halves.transpose(1, 2)


class Projection(NamedTuple):
    """The footprints of the Gaussians a camera sees (M of the N given), every tensor but ``ids`` differentiable.

    Attributes:
        ids: (M,) long, which of the N Gaussians each footprint is.
        means2d: (M, 2) the footprint's centre in pixels (u right, v down).
        conics: (M, 3) the inverse of its 2D covariance [[a, b], [b, c]] as (a, b, c).
        opacities: (M,) in (0, 1), compensated with ``antialiased``.
        depths: (M,) the mean's camera z.
        extents: (M, 2) half-width and half-height of the box outside which the footprint is not drawn: at most
            :data:`MAX_SIGMAS` standard deviations along u and v, less where the opacity fades below
            :data:`MIN_ALPHA` sooner.
    """

    ids: torch.Tensor
    means2d: torch.Tensor
    conics: torch.Tensor
    opacities: torch.Tensor
    depths: torch.Tensor
    extents: torch.Tensor


def project(means: torch.Tensor, quats: torch.Tensor, log_scales: torch.Tensor, opacities: torch.Tensor, K: torch.Tensor,
            c2w: torch.Tensor, height: int, width: int, antialiased: bool = False) -> Projection:
    """Project N Gaussians into one camera: means (N, 3), quats (N, 4), log_scales (N, 3), opacities (N,) in (0, 1),
    K (3, 3), c2w (4, 4) OpenCV -> :class:`Projection` of those in front of the near plane whose box meets the image.

    Culling is decided without gradients (which Gaussians), the footprints are computed with them. Gathers are
    ``index_select``: their backward adds into the N rows with ``index_add`` (advanced indexing's ``index_put`` with
    accumulation is several times slower on a CPU)."""
    if means.ndim != 2 or means.shape[-1] != 3 or quats.shape != (len(means), 4) or log_scales.shape != (len(means), 3) \
            or opacities.shape != (len(means),):
        raise ValueError(f"project expects means (N, 3), quats (N, 4), log_scales (N, 3), opacities (N,), got "
                         f"{tuple(means.shape)}, {tuple(quats.shape)}, {tuple(log_scales.shape)}, {tuple(opacities.shape)}")
    w2c = torch.linalg.inv(c2w)
    rotation, translation = w2c[:3, :3], w2c[:3, 3]
    with torch.no_grad():
        ids = torch.nonzero((means @ rotation.T + translation)[:, 2] > NEAR_PLANE).squeeze(1)
    points = means.index_select(0, ids) @ rotation.T + translation  # (M, 3) in the camera
    x, y, z = points.unbind(-1)
    fx, fy, cx, cy = K[0, 0], K[1, 1], K[0, 2], K[1, 2]
    # J at x / z and y / z clamped 30 % of the half field of view beyond the image's edges (gsplat's limits)
    margin_x, margin_y = 0.3 * 0.5 * width / fx, 0.3 * 0.5 * height / fy
    tx = z * (x / z).clamp(-(cx / fx + margin_x), (width - cx) / fx + margin_x)
    ty = z * (y / z).clamp(-(cy / fy + margin_y), (height - cy) / fy + margin_y)
    zeros = torch.zeros_like(z)
    jacobian = torch.stack([fx / z, zeros, -fx * tx / z**2, zeros, fy / z, -fy * ty / z**2], dim=-1).reshape(-1, 2, 3)
    in_camera = rotation @ covariances(quats.index_select(0, ids), log_scales.index_select(0, ids)) @ rotation.T  # (M, 3, 3)
    footprint = jacobian @ in_camera @ jacobian.transpose(1, 2)  # (M, 2, 2)
    a, b, c = footprint[:, 0, 0] + LOW_PASS, footprint[:, 0, 1], footprint[:, 1, 1] + LOW_PASS
    determinant = a * c - b * b
    alpha = opacities.index_select(0, ids)
    if antialiased:
        unfiltered = footprint[:, 0, 0] * footprint[:, 1, 1] - b * b
        alpha = alpha * torch.sqrt((unfiltered / determinant).clamp(min=1e-10))  # not 0: sqrt's slope there is infinite
    means2d = torch.stack([fx * x / z + cx, fy * y / z + cy], dim=-1)
    with torch.no_grad():  # which pixels a footprint may reach: a choice, not a value to differentiate
        # its box: k standard deviations along each axis, k = 3 or where o exp(-k^2 / 2) reaches 1/255
        sigmas = torch.sqrt(2.0 * torch.log((alpha / MIN_ALPHA).clamp(min=1.0))).clamp(max=MAX_SIGMAS)
        extents = sigmas[:, None] * torch.sqrt(torch.stack([a, c], dim=-1).clamp(min=0.0))
        low, high = means2d - extents, means2d + extents
        seen = (determinant > 0) & (sigmas > 0) & (high[:, 0] >= 0.5) & (low[:, 0] <= width - 0.5) \
            & (high[:, 1] >= 0.5) & (low[:, 1] <= height - 0.5)
        keep = torch.nonzero(seen).squeeze(1)
    conics = torch.stack([c, -b, a], dim=-1).index_select(0, keep) / determinant.index_select(0, keep)[:, None]
    return Projection(*(value.index_select(0, keep) for value in (ids, means2d)), conics,
                      *(value.index_select(0, keep) for value in (alpha, z, extents)))


def frame_positions(points: torch.Tensor, K: torch.Tensor, c2w: torch.Tensor, height: int, width: int,
                    near: float = NEAR_PLANE) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Where N points fall in V cameras: points (N, 3), K (V, 3, 3), c2w (V, 4, 4) OpenCV -> column (V, N) and row
    (V, N) in pixels, and in_frame (V, N) bool: in front of ``near`` and inside the image (height x width)."""
    w2c = torch.linalg.inv(c2w)
    local = points @ w2c[:, :3, :3].transpose(-1, -2) + w2c[:, None, :3, 3]  # (V, N, 3) in each camera
    z = local[..., 2]
    column = K[:, None, 0, 0] * local[..., 0] / z.clamp(min=near) + K[:, None, 0, 2]
    row = K[:, None, 1, 1] * local[..., 1] / z.clamp(min=near) + K[:, None, 1, 2]
    return column, row, (z > near) & (column >= 0) & (column < width) & (row >= 0) & (row < height)


def views_seeing(means: torch.Tensor, K: torch.Tensor, c2w: torch.Tensor, height: int, width: int,
                 chunk: int = 8) -> torch.Tensor:
    """How many of V cameras see each point: means (N, 3), K (V, 3, 3), c2w (V, 4, 4) OpenCV -> (N,) long, the views
    in whose image (height x width) a point falls in front of the near plane. The points alone, not their footprints:
    cheap enough to ask of every Gaussian for every training view at each refinement (``chunk`` views at a time)."""
    counts = torch.zeros(len(means), dtype=torch.long, device=means.device)
    c2w, K = c2w.to(means), K.to(means)
    for start in range(0, len(c2w), chunk):
        counts += frame_positions(means, K[start:start + chunk], c2w[start:start + chunk], height, width)[2].sum(dim=0)
    return counts


def inverse_sigmoid(value: float) -> float:
    """logit(value), for opacities stored as logits."""
    return math.log(value / (1.0 - value))
