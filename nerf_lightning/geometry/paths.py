"""Camera paths for novel-view videos: an orbit or a spiral around where the training cameras look, or a path through
keyframes a user framed (:func:`keyframe_path`)."""

from __future__ import annotations

import math

import torch
from kornia.geometry.conversions import rotation_matrix_to_quaternion
from kornia.geometry.quaternion import Quaternion

from nerf_lightning.geometry.cameras import look_at


def look_at_point(c2w: torch.Tensor) -> torch.Tensor:
    """The point nearest to every camera's optical axis (+z of (N, 4, 4) OpenCV c2w), by least squares: (3,).

    Solves sum_i (I - a_i a_i^T) p = sum_i (I - a_i a_i^T) o_i for camera centres o_i and unit axes a_i.
    """
    origins = c2w[:, :3, 3].double()
    axes = torch.nn.functional.normalize(c2w[:, :3, 2].double(), dim=-1)
    projectors = torch.eye(3, dtype=torch.float64) - axes[:, :, None] * axes[:, None, :]
    return torch.linalg.lstsq(projectors.sum(0), (projectors @ origins[:, :, None]).sum(0)).solution[:, 0].to(c2w.dtype)


# a capture whose cameras leave a gap wider than this around the subject is partial: paths stay on its arc
PARTIAL_GAP_DEGREES = 90.0


def _orbit_frame(c2w: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor, float, float]:
    """Centre, up and two horizontal axes of the training cameras, their mean distance and mean elevation."""
    centre = look_at_point(c2w)
    up = torch.nn.functional.normalize(-c2w[:, :3, 1].mean(0), dim=0)  # OpenCV: -y is the image's up
    offsets = c2w[:, :3, 3] - centre
    radius = float(offsets.norm(dim=-1).mean())
    elevation = float(torch.asin((torch.nn.functional.normalize(offsets, dim=-1) @ up).clamp(-1, 1)).mean())
    helper = torch.tensor([1.0, 0.0, 0.0]) if abs(float(up[0])) < 0.9 else torch.tensor([0.0, 1.0, 0.0])
    e1 = torch.nn.functional.normalize(torch.linalg.cross(up, helper.to(up)), dim=0)
    e2 = torch.linalg.cross(up, e1)
    return centre, up, e1, e2, radius, elevation


def covered_arc(c2w: torch.Tensor, centre: torch.Tensor, e1: torch.Tensor, e2: torch.Tensor) -> tuple[float, float]:
    """(start, span) in radians of the azimuths around ``centre`` (in the e1, e2 plane) that the cameras cover:
    everything but the widest gap between neighbouring cameras."""
    offsets = c2w[:, :3, 3] - centre
    azimuths = torch.sort(torch.atan2(offsets @ e2, offsets @ e1)).values
    gaps = torch.cat([azimuths[1:] - azimuths[:-1], (azimuths[:1] + 2.0 * math.pi) - azimuths[-1:]])
    widest = int(gaps.argmax())
    return float(azimuths[(widest + 1) % len(azimuths)]), 2.0 * math.pi - float(gaps[widest])


def _azimuths(c2w, centre, e1, e2, u: torch.Tensor, turns: int) -> torch.Tensor:
    """Azimuths at path positions u in [0, 1): ``turns`` full circles, or, for a partial capture (a gap wider than
    :data:`PARTIAL_GAP_DEGREES`), ``turns`` sweeps there and back along the arc the cameras cover."""
    start, span = covered_arc(c2w, centre, e1, e2)
    if 2.0 * math.pi - span <= math.radians(PARTIAL_GAP_DEGREES):
        return 2.0 * math.pi * turns * u
    return start + span * 0.5 * (1.0 - torch.cos(2.0 * math.pi * turns * u))


def orbit_path(c2w: torch.Tensor, n_frames: int = 60, elevation_degrees: float | None = None) -> torch.Tensor:
    """(n_frames, 4, 4) OpenCV cameras circling the training cameras' look-at point once, at their mean
    distance and (unless given) mean elevation, looking at that point with the training cameras' up; for a
    partial capture, there and back along the arc its cameras cover."""
    centre, up, e1, e2, radius, elevation = _orbit_frame(c2w)
    if elevation_degrees is not None:
        elevation = math.radians(elevation_degrees)
    theta = _azimuths(c2w, centre, e1, e2, torch.linspace(0.0, 1.0, n_frames + 1)[:-1], turns=1)
    phi = torch.full_like(theta, elevation)
    return _cameras_on_sphere(centre, up, e1, e2, radius, theta, phi)


def spiral_path(c2w: torch.Tensor, n_frames: int = 60, turns: int = 2, swing_degrees: float = 15.0) -> torch.Tensor:
    """(n_frames, 4, 4) cameras on ``turns`` circles around the look-at point (sweeps along the covered arc, for
    a partial capture) whose elevation swings ``swing_degrees`` above and below the cameras' mean elevation."""
    centre, up, e1, e2, radius, elevation = _orbit_frame(c2w)
    u = torch.linspace(0.0, 1.0, n_frames + 1)[:-1]
    theta = _azimuths(c2w, centre, e1, e2, u, turns)
    phi = elevation + math.radians(swing_degrees) * torch.sin(2.0 * math.pi * u)
    return _cameras_on_sphere(centre, up, e1, e2, radius, theta, phi)


def _cameras_on_sphere(centre, up, e1, e2, radius, theta, phi) -> torch.Tensor:
    directions = torch.cos(phi)[:, None] * (torch.cos(theta)[:, None] * e1 + torch.sin(theta)[:, None] * e2) + torch.sin(phi)[:, None] * up
    return look_at(centre + radius * directions, target=centre, up=up)


def keyframe_path(c2w: torch.Tensor, fov_degrees: torch.Tensor, n_frames: int) -> tuple[torch.Tensor, torch.Tensor]:
    """``n_frames`` cameras through K >= 2 keyframes, c2w (K, 4, 4) and vertical fields of view ``fov_degrees`` (K,),
    each keyframe an equal share of the time, the first frame the first keyframe and the last the last:
    -> c2w (n_frames, 4, 4), fov (n_frames,).

    Positions follow a Catmull-Rom spline through the keyframes (smooth at each, the end keyframes repeated for the
    end tangents), rotations are spherically interpolated between consecutive keyframes (kornia's ``slerp``, the
    shorter arc), and the field of view linearly. The matrices' convention (OpenCV or OpenGL) is kept."""
    if c2w.ndim != 3 or c2w.shape[1:] != (4, 4) or len(c2w) < 2:
        raise ValueError(f"a keyframe path needs at least two keyframes of shape (4, 4), got {tuple(c2w.shape)}")
    if fov_degrees.shape != (len(c2w),):
        raise ValueError(f"a keyframe path needs one field of view a keyframe: {len(c2w)} keyframes, fov of shape {tuple(fov_degrees.shape)}")
    if n_frames < 2:
        raise ValueError(f"a keyframe path needs at least 2 frames, got {n_frames}")
    c2w, fov_degrees = c2w.double(), fov_degrees.double()
    last = len(c2w) - 1
    u = torch.linspace(0.0, float(last), n_frames, dtype=torch.float64)
    segment = u.floor().long().clamp(max=last - 1)  # frame f lies between keyframes segment[f] and segment[f] + 1
    t = (u - segment)[:, None]
    positions = c2w[:, :3, 3]
    padded = torch.cat([positions[:1], positions, positions[-1:]])  # p_{-1} = p_0, p_{K} = p_{K-1}
    p0, p1, p2, p3 = (padded[segment + k] for k in range(4))
    # the uniform Catmull-Rom segment between p1 and p2: through both, tangents (p2 - p0) / 2 and (p3 - p1) / 2
    position = 0.5 * ((2.0 * p1) + (p2 - p0) * t + (2.0 * p0 - 5.0 * p1 + 4.0 * p2 - p3) * t**2 + (3.0 * p1 - p0 - 3.0 * p2 + p3) * t**3)
    quaternions = rotation_matrix_to_quaternion(c2w[:, :3, :3].contiguous())  # (K, 4) wxyz
    start, end = Quaternion(quaternions[segment]), Quaternion(quaternions[segment + 1])
    rotation = start.slerp(end, t[:, 0]).matrix()
    out = torch.eye(4, dtype=torch.float64).repeat(n_frames, 1, 1)
    out[:, :3, :3], out[:, :3, 3] = rotation, position
    fov = fov_degrees[segment] + (fov_degrees[segment + 1] - fov_degrees[segment]) * t[:, 0]
    return out.float(), fov.float()
