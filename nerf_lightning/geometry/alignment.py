"""Comparing two sets of cameras of one capture: the similarity that best maps one set's centres onto the other's
(Umeyama's least squares, fitted again without the cameras far off it), and the position and rotation errors left
after it.

Structure from motion recovers cameras up to a similarity (its own origin, orientation and scale), so poses from
two runs (recovered by ``nerf-process-data`` and published with a data set, say) are compared after aligning them.
"""

from __future__ import annotations

import torch

# a camera whose centre lies over this many times the median camera's distance from its reference after a fit, and
# over FAR_OFF of the cameras' spread, is left out of the next fit: one camera posed wrong (hundreds of percent of the
# spread) would otherwise pull the least squares fit, and with it every other camera's error (as COLMAP's
# model_aligner fits by RANSAC, not by all). FAR_OFF keeps a good model's ordinary worst cameras in the fit
OUTLIER_FACTOR = 3.0
FAR_OFF = 0.05
REFITS = 5


def umeyama_similarity(source: torch.Tensor, target: torch.Tensor) -> torch.Tensor:
    """The similarity ``T`` (4, 4) that minimises sum_i |T source_i - target_i|^2 over scale, rotation and translation.

    Umeyama (1991), "Least-squares estimation of transformation parameters between two point patterns": the rotation
    from the SVD of the cross-covariance, with the sign fixed so that it is a rotation (det +1), not a reflection.

    Args:
        source: (N, 3) points, N >= 3 and not all on one line.
        target: (N, 3) the points they should land on.
    Returns:
        (4, 4) float64: ``[[s R, t], [0, 1]]``, target ~ s R source + t.
    """
    if source.ndim != 2 or source.shape[-1] != 3 or source.shape != target.shape:
        raise ValueError(f"umeyama_similarity: expected two (N, 3) point sets of the same N, got {tuple(source.shape)} and {tuple(target.shape)}")
    if source.shape[0] < 3:
        raise ValueError(f"umeyama_similarity: needs at least 3 points, got {source.shape[0]}")
    source, target = source.double(), target.double()
    source_mean, target_mean = source.mean(0), target.mean(0)
    source_centred, target_centred = source - source_mean, target - target_mean
    covariance = target_centred.T @ source_centred / source.shape[0]
    U, singular, Vh = torch.linalg.svd(covariance)
    sign = torch.ones(3, dtype=torch.float64)
    if torch.linalg.det(U) * torch.linalg.det(Vh) < 0:
        sign[2] = -1.0
    rotation = U @ torch.diag(sign) @ Vh
    source_variance = source_centred.pow(2).sum(1).mean()
    if source_variance < 1e-18:
        raise ValueError("umeyama_similarity: the source points all coincide")
    scale = (singular * sign).sum() / source_variance
    transform = torch.eye(4, dtype=torch.float64)
    transform[:3, :3] = scale * rotation
    transform[:3, 3] = target_mean - scale * rotation @ source_mean
    return transform


def rotation_angle(rotation_a: torch.Tensor, rotation_b: torch.Tensor) -> torch.Tensor:
    """(N, 3, 3), (N, 3, 3) rotations -> (N,) the angle of ``a^T b`` in degrees: how far apart they turn."""
    relative = rotation_a.transpose(-1, -2) @ rotation_b
    cosine = ((relative.diagonal(dim1=-2, dim2=-1).sum(-1) - 1.0) / 2.0).clamp(-1.0, 1.0)
    return torch.rad2deg(torch.arccos(cosine))


def camera_pose_errors(c2w: torch.Tensor, c2w_reference: torch.Tensor) -> dict[str, torch.Tensor]:
    """Cameras ``c2w`` compared with the same cameras in a reference, after the similarity that best aligns their centres.

    Both sets must use the same camera convention (both OpenGL or both OpenCV); row i of each is the same photo.

    Args:
        c2w: (N, 4, 4) camera-to-world matrices, N >= 3, in any similarity frame.
        c2w_reference: (N, 4, 4) the reference's camera-to-world matrices of the same N photos.
    The similarity is fitted to all centres, then again without those over :data:`OUTLIER_FACTOR` times the median
    distance of the fit and over :data:`FAR_OFF` of the spread (at most :data:`REFITS` times, never on fewer than half
    of them): the errors of cameras left out are still reported, after the fit to the others.

    Returns:
        ``transform`` (4, 4): reference-from-c2w similarity (:func:`umeyama_similarity` of the centres it was fitted to);
        ``aligned_on`` (N,) bool: the cameras it was fitted to;
        ``position_error`` (N,): distance of each aligned centre from its reference, in the reference's units;
        ``rotation_error`` (N,): degrees between each aligned camera rotation and the reference's;
        ``spread`` (): the root mean square distance of the reference centres from their mean, the scale that
        position errors are judged against.
    """
    if c2w.shape != c2w_reference.shape or c2w.ndim != 3 or c2w.shape[-2:] != (4, 4):
        raise ValueError(f"camera_pose_errors: expected two (N, 4, 4) camera sets of the same N, got {tuple(c2w.shape)} and {tuple(c2w_reference.shape)}")
    c2w, c2w_reference = c2w.double(), c2w_reference.double()
    reference_centres = c2w_reference[:, :3, 3]
    spread = (reference_centres - reference_centres.mean(0)).pow(2).sum(-1).mean().sqrt()
    aligned_on = torch.ones(len(c2w), dtype=torch.bool)
    transform = umeyama_similarity(c2w[:, :3, 3], reference_centres)
    for fit in range(REFITS + 1):
        centres = c2w[:, :3, 3] @ transform[:3, :3].T + transform[:3, 3]
        distance = (centres - reference_centres).norm(dim=-1)
        within = distance <= max(OUTLIER_FACTOR * float(distance[aligned_on].median()), FAR_OFF * float(spread))
        if fit == REFITS or torch.equal(within, aligned_on) or 2 * int(within.sum()) < len(c2w) or int(within.sum()) < 3:
            break
        try:
            refitted = umeyama_similarity(c2w[within, :3, 3], reference_centres[within])
        except ValueError:  # the kept centres all coincide: the fit before stands
            break
        transform, aligned_on = refitted, within
    scaled_rotation = transform[:3, :3]
    scale = torch.linalg.det(scaled_rotation) ** (1.0 / 3.0)
    rotations = (scaled_rotation / scale) @ c2w[:, :3, :3]
    return {
        "transform": transform,
        "aligned_on": aligned_on,
        "position_error": (centres - reference_centres).norm(dim=-1),
        "rotation_error": rotation_angle(rotations, c2w_reference[:, :3, :3]),
        "spread": spread,
    }
