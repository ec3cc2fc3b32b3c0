"""Pinhole cameras on kornia.

Conventions, named once: a camera-to-world matrix ``c2w`` (4, 4) maps camera coordinates to world
coordinates. ``opencv`` cameras look down +z with x right and y down (kornia's and the course's
convention); ``opengl`` cameras (Blender, NeRF's synthetic data, nerfstudio) look down -z with y up.
Loaders convert to OpenCV once, with :func:`opengl_to_opencv`; all code after them speaks OpenCV.
Pixel (u, v) has u to the right and v down, and the centre of pixel (i, j) is at (j + 0.5, i + 0.5).
"""

from __future__ import annotations

import kornia
import torch
from kornia.geometry.camera import PinholeCamera
from kornia.geometry.camera.perspective import unproject_points

# flips the y and z axes of a camera frame: OpenGL (y up, z back) <-> OpenCV (y down, z forward)
_FLIP_YZ = torch.diag(torch.tensor([1.0, -1.0, -1.0, 1.0]))


def opengl_to_opencv(c2w: torch.Tensor) -> torch.Tensor:
    """(..., 4, 4) OpenGL camera-to-world -> (..., 4, 4) OpenCV camera-to-world (its own inverse)."""
    return c2w @ _FLIP_YZ.to(c2w)


def validate_c2w(c2w: torch.Tensor, source: str, tolerance: float = 1e-3) -> torch.Tensor:
    """Check (N, 4, 4) camera-to-world matrices: finite, last row [0, 0, 0, 1], rotation orthonormal with det +1.

    Raises ValueError naming ``source`` (a file and key) and the first bad camera.
    """
    if c2w.ndim != 3 or c2w.shape[-2:] != (4, 4):
        raise ValueError(f"{source}: expected camera-to-world matrices of shape (N, 4, 4), got {tuple(c2w.shape)}")
    c2w = c2w.to(torch.float64)
    bad = ~torch.isfinite(c2w).flatten(1).all(1)
    if bad.any():
        raise ValueError(f"{source}: camera {int(bad.nonzero()[0])} has non-finite entries (NaN or inf)")
    last_row = (c2w[:, 3] - torch.tensor([0.0, 0.0, 0.0, 1.0], dtype=torch.float64)).abs().amax(1)
    if (last_row > tolerance).any():
        raise ValueError(f"{source}: camera {int((last_row > tolerance).nonzero()[0])} has last row {c2w[int((last_row > tolerance).nonzero()[0]), 3].tolist()}, expected [0, 0, 0, 1]")
    rotation = c2w[:, :3, :3]
    error = (rotation.transpose(1, 2) @ rotation - torch.eye(3, dtype=torch.float64)).abs().flatten(1).amax(1)
    error = torch.maximum(error, (torch.linalg.det(rotation) - 1.0).abs())
    if (error > tolerance).any():
        index = int((error > tolerance).nonzero()[0])
        raise ValueError(f"{source}: camera {index} is not rigid: its rotation is not orthonormal with determinant +1 (error {float(error[index]):.3g})")
    return c2w.to(torch.float32)


def centred_intrinsics(focal: torch.Tensor, height: int, width: int) -> torch.Tensor:
    """(N,) focal lengths in pixels -> (N, 3, 3) intrinsics with the principal point at the image's centre (a camera
    path's frames: nerfstudio's, and the viewer's keyframes)."""
    K = torch.zeros(len(focal), 3, 3, dtype=focal.dtype)
    K[:, 0, 0], K[:, 1, 1], K[:, 0, 2], K[:, 1, 2], K[:, 2, 2] = focal, focal, 0.5 * width, 0.5 * height, 1.0
    return K


def pinhole_camera(K: torch.Tensor, c2w: torch.Tensor, height: int, width: int) -> PinholeCamera:
    """kornia cameras from (B, 3, 3) intrinsics and (B, 4, 4) OpenCV camera-to-world matrices."""
    batch = K.shape[0]
    intrinsics = torch.eye(4, dtype=K.dtype, device=K.device).repeat(batch, 1, 1)
    intrinsics[:, :3, :3] = K
    extrinsics = torch.linalg.inv(c2w)  # kornia's extrinsics map world to camera
    size = torch.full((batch,), 1, dtype=K.dtype, device=K.device)
    return PinholeCamera(intrinsics, extrinsics, size * height, size * width)


def camera_to_world(c2w: torch.Tensor, x_c: torch.Tensor) -> torch.Tensor:
    """Points from camera to world coordinates.

    Batched: c2w (B, 4, 4) and x_c (B, N, 3) -> (B, N, 3). The course's unbatched shapes: x_c (N, 3) with one
    camera c2w (4, 4), or with a camera per point c2w (N, 4, 4) -> (N, 3).
    """
    if x_c.ndim == 2:
        if c2w.ndim == 2:
            return kornia.geometry.transform_points(c2w[None], x_c[None])[0]
        _check_per_point(c2w, x_c, "c2w", (4, 4))
        return kornia.geometry.transform_points(c2w, x_c[:, None])[:, 0]
    return kornia.geometry.transform_points(c2w, x_c)


def pixel_to_camera(K: torch.Tensor, uv: torch.Tensor, s: torch.Tensor | float) -> torch.Tensor:
    """Pixels to camera coordinates at depth ``s`` (the camera-frame z): x_c = s K^-1 [u, v, 1].

    Batched: K (B, 3, 3), uv (B, N, 2), s a number or (B, N, 1) -> (B, N, 3). The course's unbatched shapes:
    K (3, 3) or (N, 3, 3), uv (N, 2), s a number, (N,) or (N, 1) -> (N, 3).
    """
    if uv.ndim == 2:
        depth = _depth_on(uv, s)
        depth = depth[:, None] if depth.ndim == 1 else depth
        if K.ndim == 3:
            _check_per_point(K, uv, "K", (3, 3))
            return pixel_to_camera(K, uv[:, None], depth.expand(len(uv), 1)[:, None])[:, 0]
        return pixel_to_camera(K[None], uv[None], depth.expand(len(uv), 1)[None])[0]
    depth = _depth_on(uv, s).expand(*uv.shape[:-1], 1)
    return unproject_points(uv, depth, K[:, None])


def _depth_on(uv: torch.Tensor, s: torch.Tensor | float) -> torch.Tensor:
    """``s`` as a tensor of ``uv``'s dtype on its device; a number made there by a fill: ``torch.as_tensor`` of a
    number makes it on the host and copies it over, and on a GPU that copy makes the host wait (each training batch's
    rays come through here: one wait a step)."""
    if isinstance(s, (int, float)):
        return uv.new_full((), float(s))
    return torch.as_tensor(s, dtype=uv.dtype, device=uv.device)


def pixel_to_ray(K: torch.Tensor, c2w: torch.Tensor, uv: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Rays through pixels: rays_o, rays_d, the camera centre and the unit direction from it through the pixel's
    point at depth 1.

    Batched: K (B, 3, 3), c2w (B, 4, 4) OpenCV, uv (B, N, 2) -> (B, N, 3) each. The course's unbatched shapes:
    K (3, 3), c2w (4, 4) for one camera or (N, 4, 4) for a camera per pixel, uv (N, 2) -> (N, 3) each.
    """
    if uv.ndim == 2:
        x_c = pixel_to_camera(K, uv, 1.0)  # (N, 3)
        rays_o = (c2w[:3, 3] if c2w.ndim == 2 else c2w[:, :3, 3]).expand(len(uv), 3)
        return rays_o, torch.nn.functional.normalize(camera_to_world(c2w, x_c) - rays_o, dim=-1)
    rays_o = c2w[:, None, :3, 3].expand(*uv.shape[:-1], 3)
    x_w = camera_to_world(c2w, pixel_to_camera(K, uv, 1.0))
    rays_d = torch.nn.functional.normalize(x_w - rays_o, dim=-1)
    return rays_o, rays_d


def _check_per_point(matrices: torch.Tensor, points: torch.Tensor, name: str, shape: tuple[int, int]) -> None:
    if matrices.shape != (len(points), *shape):
        raise ValueError(f"{name} of shape {tuple(matrices.shape)} with {len(points)} points: expected one {shape} matrix "
                         f"or one for each point, ({len(points)}, {shape[0]}, {shape[1]})")


def look_at(eye: torch.Tensor, target: torch.Tensor | None = None, up: torch.Tensor | None = None) -> torch.Tensor:
    """OpenCV camera-to-world matrices of cameras at ``eye`` (N, 3) looking at ``target`` (3,) (default origin).

    ``up`` (default +z) sets the image's up direction (-y of the camera); returns (N, 4, 4).
    """
    target = torch.zeros(3, dtype=eye.dtype) if target is None else target
    up = torch.tensor([0.0, 0.0, 1.0], dtype=eye.dtype) if up is None else up
    forward = torch.nn.functional.normalize(target - eye, dim=-1)  # camera +z
    right = torch.linalg.cross(forward, up.expand_as(forward))
    # looking straight along `up`: any right vector will do
    degenerate = right.norm(dim=-1) < 1e-6
    right[degenerate] = torch.linalg.cross(forward[degenerate], torch.tensor([0.0, 1.0, 0.0], dtype=eye.dtype).expand_as(forward[degenerate]))
    right = torch.nn.functional.normalize(right, dim=-1)  # camera +x
    down = torch.linalg.cross(forward, right)  # camera +y
    c2w = torch.eye(4, dtype=eye.dtype).repeat(eye.shape[0], 1, 1)
    c2w[:, :3, 0], c2w[:, :3, 1], c2w[:, :3, 2], c2w[:, :3, 3] = right, down, forward, eye
    return c2w


def box_pixel_rectangles(K: torch.Tensor, c2w: torch.Tensor, height: int, width: int, box: torch.Tensor) -> torch.Tensor:
    """(V, 4) long: for each of V OpenCV cameras K (V, 3, 3), c2w (V, 4, 4), the pixel rectangle (x0, y0, x1, y1),
    columns x0 <= j < x1 and rows y0 <= i < y1, that holds every pixel whose ray meets the box (6,)
    (xmin, ymin, zmin, xmax, ymax, zmax): the bounds of the box's 8 corners projected, widened by a pixel and cut to
    the view. A view with a corner at or behind its camera's plane (the camera inside the box, or beside it) gets
    the whole view, as does one whose rectangle would be empty (the box out of sight)."""
    low, high = box[:3].double(), box[3:].double()
    corners = torch.stack(torch.meshgrid(*[torch.stack([low[axis], high[axis]]) for axis in range(3)], indexing="ij"), -1).reshape(8, 3)
    corners = corners.expand(K.shape[0], 8, 3)  # (V, 8, 3): the same corners seen by each camera
    camera = pinhole_camera(K.double(), c2w.double(), height, width)
    z = kornia.geometry.transform_points(camera.extrinsics, corners)[..., 2]  # (V, 8) camera-frame depths
    uv = camera.project(corners)  # (V, 8, 2); a corner at or behind the camera's plane gives the whole view below
    # pixel j covers u in [j, j + 1): floor of the least u, and one past the floor of the greatest
    x0 = (uv[..., 0].amin(1).floor() - 1).clamp(0, width)
    y0 = (uv[..., 1].amin(1).floor() - 1).clamp(0, height)
    x1 = (uv[..., 0].amax(1).floor() + 2).clamp(0, width)
    y1 = (uv[..., 1].amax(1).floor() + 2).clamp(0, height)
    rectangles = torch.stack([x0, y0, x1, y1], -1).long()
    whole = (z <= 1e-6 * (high - low).norm()).any(1) | (rectangles[:, 2] <= rectangles[:, 0]) | (rectangles[:, 3] <= rectangles[:, 1])
    rectangles[whole] = torch.tensor([0, 0, width, height])
    return rectangles


def pixel_ray_lengths(K: torch.Tensor, height: int, width: int) -> torch.Tensor:
    """(H, W): how far along a pixel's ray (a unit direction) the plane z = 1 lies, |K^-1 [u, v, 1]|, so that a
    camera z (a splat's depth, a phone's z-depth map) times it is the distance the project's rays measure depth in
    (:func:`pixel_to_ray`)."""
    v, u = torch.meshgrid(torch.arange(height, device=K.device, dtype=K.dtype) + 0.5,
                          torch.arange(width, device=K.device, dtype=K.dtype) + 0.5, indexing="ij")
    x, y = (u - K[0, 2]) / K[0, 0], (v - K[1, 2]) / K[1, 1]
    return torch.sqrt(x * x + y * y + 1.0)
