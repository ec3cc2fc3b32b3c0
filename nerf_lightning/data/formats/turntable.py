"""A procedural turntable capture: the object turns, the camera and the room stand still.

Small objects are often photographed on a turntable. Structure from motion assumes a static scene, so the room's
features say the camera never moved; only the object's features (the photos' masks) pose the photos relative to the
object. This capture, ray-traced in float64 like the procedural scene and small enough for CI, shows exactly that:

- the object: spheres and boxes on a turning disc, within radius 1 of the turntable's axis (the room's z axis),
  coloured by multi-octave 3D value noise in the OBJECT's frame and lit (ambient + Lambert) by a light that turns
  with it, so that in the object's frame it is a static scene a NeRF can fit;
- the room: walls 5 units from the axis, floor, ceiling and the static pedestal under the disc, coloured by coarser
  noise in the ROOM's frame, so that without masks it gives most of a photo's features;
- the cameras: ``rings`` heights (elevations from 15 to 35 degrees) 3.2 units from the object, a 45 degree field of
  view, each ring photographing ``n_photos / rings`` turn angles evenly spaced (rings offset by a fraction of a
  step); 2x2 supersampled, a pixel is the object's where at least 2 of its 4 samples hit the object. With
  ``fisheye`` (k1..k4), a Kannala-Brandt lens (``OPENCV_FISHEYE``) whose photo spans ``fov_degrees`` across: a GoPro's
  capture, for nerf-process-data's fisheye posing.

Written: ``images/turn_000.png`` ... (RGB), ``masks/turn_000.png`` (8-bit, 255 on the object), ``transforms.json``
(nerfstudio's layout: each photo's OpenGL camera-to-world in the object's frame, what a reconstruction of the masked
photos gives up to a similarity, and its ``mask_path``) and ``turntable.json`` (turn angles, rings, and the cameras
in the room's frame, standing still within each ring: what the room's features say). Deterministic: the same
arguments give the same bytes.

With ``masks/`` as pycolmap's ``ImageReaderOptions.mask_path`` (4.2 finds ``<image name>`` there as well as COLMAP's
``<image name>.png``), exhaustive matching and either mapper pose every one of the 36 default photos within 1 % of
the cameras' spread and 1 degree; without masks the poses are those of a camera standing still, or wrong. 36 photos,
not more, because the unmasked reconstruction's bundle adjustments grow slow on a scene they cannot explain.
"""

from __future__ import annotations

import math
from pathlib import Path

import torch
from kornia.geometry.camera import undistort_points_kannala_brandt

from nerf_lightning.data.formats.lenses import FISHEYE_KEYS, fisheye_radius
from nerf_lightning.data.formats.shared import default_cache, rendered_once
from nerf_lightning.data.formats.transforms import load_transforms
from nerf_lightning.data.scene import Scene
from nerf_lightning.geometry.cameras import look_at, opengl_to_opencv
from nerf_lightning.geometry.rays import image_pixels, image_rays
from nerf_lightning.io import write_json, write_png

VERSION = 1  # bump when the capture changes, so caches are rebuilt

# the object, in its own frame (z up along the turntable's axis): (centre, radius) and (centre, half size)
SPHERES = (((0.35, 0.15, -0.20), 0.45), ((-0.40, -0.20, 0.27), 0.22), ((-0.25, 0.55, -0.48), 0.17))
BOXES = (((-0.40, -0.20, -0.30), (0.28, 0.22, 0.35)), ((0.15, -0.55, -0.25), (0.14, 0.14, 0.40)))
DISC = (1.0, -0.75, -0.65)  # radius, bottom, top: the turning plate, part of the object
OBJECT_BOUNDS = ((-1.0, -1.0, -0.75), (1.0, 1.0, 0.5))  # a box around all of it
TARGET = (0.0, 0.0, -0.25)  # where the cameras look
ELEVATIONS = (15.0, 35.0)  # degrees above the target of the lowest and the highest ring
OBJECT_LIGHT = (0.5, -0.4, 0.8)  # fixed to the object: it turns with it
OBJECT_TEXTURE = (1, 10.0)  # noise seed and cells a unit: SIFT needs this fine a pattern to pose the photos well
# the room, in its own frame: the walls, floor and ceiling box, and the pedestal the disc turns on
ROOM = ((-5.0, -5.0, -1.6), (5.0, 5.0, 3.5))
PEDESTAL = ((-0.7, -0.7, -1.6), (0.7, 0.7, -0.75))
ROOM_LIGHT = (0.3, 0.2, 1.0)
ROOM_TEXTURE = (2, 1.5)
NO_HIT = math.inf
PHOTOS_A_BATCH = 6  # rays of this many photos are traced together: fewer, larger tensor operations


def _closest(hits: list[tuple[torch.Tensor, torch.Tensor]]) -> tuple[torch.Tensor, torch.Tensor]:
    """The nearest of several (t (N,), normal (N, 3)) hits, ray by ray."""
    t, normal = hits[0]
    for t_other, normal_other in hits[1:]:
        closer = t_other < t
        t, normal = torch.where(closer, t_other, t), torch.where(closer[:, None], normal_other, normal)
    return t, normal


def _sphere(o: torch.Tensor, d: torch.Tensor, centre: tuple, radius: float) -> tuple[torch.Tensor, torch.Tensor]:
    oc = o - torch.tensor(centre, dtype=o.dtype)
    b = (oc * d).sum(-1)
    disc = b * b - (oc * oc).sum(-1) + radius**2
    t = -b - torch.sqrt(disc.clamp(min=0))
    t = torch.where((disc >= 0) & (t > 1e-9), t, NO_HIT)
    return t, (oc + t.nan_to_num(posinf=0.0)[:, None] * d) / radius


def _box(o: torch.Tensor, d: torch.Tensor, lo: tuple, hi: tuple, inside: bool = False) -> tuple[torch.Tensor, torch.Tensor]:
    """Where rays (N, 3) enter a box from outside, or leave it from ``inside``; normals face the ray's origin."""
    inv = 1.0 / torch.where(d.abs() < 1e-12, 1e-12, d)
    t0, t1 = (torch.tensor(lo, dtype=o.dtype) - o) * inv, (torch.tensor(hi, dtype=o.dtype) - o) * inv
    t_near, t_far = torch.minimum(t0, t1), torch.maximum(t0, t1)
    (t, axis), t_other = (t_far.min(dim=-1), t_near.amax(dim=-1)) if inside else (t_near.max(dim=-1), t_far.amin(dim=-1))
    hit = (t > 1e-9) & ((t_other <= t) if inside else (t <= t_other))
    normal = torch.zeros_like(o)
    normal[torch.arange(len(o)), axis] = -torch.sign(d[torch.arange(len(o)), axis])
    return torch.where(hit, t, NO_HIT), normal


def _disc(o: torch.Tensor, d: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Rays (N, 3) against the capped cylinder of :data:`DISC` about the z axis, from outside."""
    radius, bottom, top = DISC
    a = (d[:, :2] ** 2).sum(-1).clamp(min=1e-18)
    b = (o[:, :2] * d[:, :2]).sum(-1)
    disc = b * b - a * ((o[:, :2] ** 2).sum(-1) - radius**2)
    t_side = (-b - torch.sqrt(disc.clamp(min=0))) / a
    z = o[:, 2] + t_side * d[:, 2]
    t_side = torch.where((disc >= 0) & (t_side > 1e-9) & (z >= bottom) & (z <= top), t_side, NO_HIT)
    side_normal = torch.nn.functional.pad((o[:, :2] + t_side.nan_to_num(posinf=0.0)[:, None] * d[:, :2]) / radius, (0, 1))
    hits = [(t_side, side_normal)]
    for height in (bottom, top):
        t = (height - o[:, 2]) / torch.where(d[:, 2].abs() < 1e-12, 1e-12, d[:, 2])
        inside = ((o[:, :2] + t[:, None] * d[:, :2]) ** 2).sum(-1) <= radius**2
        normal = torch.zeros_like(o)
        normal[:, 2] = -torch.sign(d[:, 2])
        hits.append((torch.where(inside & (t > 1e-9), t, NO_HIT), normal))
    return _closest(hits)


def trace_object(o: torch.Tensor, d: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Rays (N, 3) in the object's frame -> first hit t (N,) (inf on a miss) and normal (N, 3) on the object."""
    t, normal = torch.full((len(o),), NO_HIT, dtype=o.dtype), torch.zeros_like(o)
    near = torch.isfinite(_box(o, d, *OBJECT_BOUNDS)[0])  # only these rays can hit the object: trace them alone
    o, d = o[near], d[near]
    hits = [_sphere(o, d, centre, radius) for centre, radius in SPHERES] + [_disc(o, d)]
    hits += [_box(o, d, tuple(c - h for c, h in zip(centre, half)), tuple(c + h for c, h in zip(centre, half))) for centre, half in BOXES]
    t[near], normal[near] = _closest(hits)
    return t, normal


def trace_room(o: torch.Tensor, d: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Rays (N, 3) from inside the room, in its frame -> first hit t (N,) and normal (N, 3) on the room or pedestal."""
    return _closest([_box(o, d, *ROOM, inside=True), _box(o, d, *PEDESTAL)])


def texture(points: torch.Tensor, seed: int, frequency: float, octaves: int = 4, period: int = 64) -> torch.Tensor:
    """Colours (N, 3) in [0, 1] of (N, 3) points: multi-octave 3D value noise (a random lattice repeating every
    ``period`` cells), darkened in sharp-edged spots so that SIFT finds corners and blobs at every scale."""
    lattice = torch.rand(1, 4, period, period, period, generator=torch.Generator().manual_seed(seed))
    lattice = torch.nn.functional.pad(lattice, (0, 1, 0, 1, 0, 1), mode="circular")  # the first cell again past the last
    total = torch.zeros(4, len(points))
    for octave in range(octaves):
        p = points * (frequency * 2**octave) + 17.0 * octave
        cell, f = p.floor(), p - p.floor()
        # smoothstep between lattice points (no creases at the cells' faces), then trilinear interpolation
        q = cell.remainder(period) + f * f * (3.0 - 2.0 * f)
        grid = (q * (2.0 / period) - 1.0).float().view(1, 1, 1, -1, 3)
        total += 0.55**octave * torch.nn.functional.grid_sample(lattice, grid, align_corners=True).view(4, -1)
    total = total.T / sum(0.55**octave for octave in range(octaves))
    colour = ((total[:, :3] - 0.5) * 3.0 + 0.5).clamp(0, 1)
    return (colour * torch.where(total[:, 3:] > 0.6, 0.2, 1.0)).double()


def _lambert(normal: torch.Tensor, light: tuple) -> torch.Tensor:
    direction = torch.nn.functional.normalize(torch.tensor(light, dtype=torch.float64), dim=0)
    return (0.6 + 0.4 * (normal @ direction).clamp(min=0))[:, None]


def turn_about_z(angles: torch.Tensor) -> torch.Tensor:
    """(B, 4, 4) rotations by ``angles`` (B,) radians about z: room-from-object of an object turned by each angle."""
    c, s = torch.cos(angles.double()), torch.sin(angles.double())
    rotation = torch.eye(4, dtype=torch.float64).repeat(len(angles), 1, 1)
    rotation[:, 0, 0], rotation[:, 0, 1], rotation[:, 1, 0], rotation[:, 1, 1] = c, -s, s, c
    return rotation


def camera_rays(K: torch.Tensor, c2w: torch.Tensor, height: int, width: int,
                fisheye: tuple[float, float, float, float] | None = None) -> tuple[torch.Tensor, torch.Tensor]:
    """Rays (B, H W, 3) each of cameras K (3, 3) at OpenCV c2w (B, 4, 4): pinholes, or with ``fisheye`` (k1..k4)
    Kannala-Brandt lenses, each pixel centre undistorted onto z = 1 by kornia (the lens seeing under 90 degrees off
    axis)."""
    if fisheye is None:
        return image_rays(K.expand(len(c2w), 3, 3), c2w, height, width)
    parameters = torch.tensor([K[0, 0], K[1, 1], K[0, 2], K[1, 2], *fisheye], dtype=torch.float64)
    on_plane = undistort_points_kannala_brandt(image_pixels(height, width).double(), parameters)  # (H W, 2)
    directions = torch.nn.functional.normalize(torch.cat([on_plane, torch.ones_like(on_plane[:, :1])], dim=-1), dim=-1)
    d = directions @ c2w[:, :3, :3].transpose(1, 2)  # (B, H W, 3)
    return c2w[:, None, :3, 3].expand_as(d), d


def render_photos(K: torch.Tensor, c2w: torch.Tensor, turns: torch.Tensor, height: int, width: int,
                  fisheye: tuple[float, float, float, float] | None = None) -> tuple[torch.Tensor, torch.Tensor]:
    """Photos: K (3, 3), OpenCV c2w (B, 4, 4) in the room's frame, the object turned by ``turns`` (B,) radians about z,
    through pinholes or ``fisheye`` lenses (:func:`camera_rays`) -> rgb (B, H, W, 3) float in [0, 1] and the object's
    masks (B, H, W) bool, from 2x2 samples a pixel."""
    batch = len(c2w)
    K2 = torch.diag(torch.tensor([2.0, 2.0, 1.0], dtype=torch.float64)) @ K.double()  # samples at 1/4 and 3/4 of a pixel
    o, d = camera_rays(K2, c2w.double(), 2 * height, 2 * width, fisheye)  # (B, 4 H W, 3)
    room_from_object = turn_about_z(turns)[:, :3, :3]
    o_object, d_object = (o @ room_from_object).reshape(-1, 3), (d @ room_from_object).reshape(-1, 3)  # row vectors: R^T x
    o, d = o.reshape(-1, 3), d.reshape(-1, 3)
    t_object, normal_object = trace_object(o_object, d_object)
    t_room, normal_room = trace_room(o, d)
    on_object = t_object < t_room
    rgb = torch.empty_like(o)
    points = o_object[on_object] + t_object[on_object, None] * d_object[on_object]
    rgb[on_object] = texture(points, *OBJECT_TEXTURE) * _lambert(normal_object[on_object], OBJECT_LIGHT)
    room = ~on_object
    rgb[room] = texture(o[room] + t_room[room, None] * d[room], *ROOM_TEXTURE) * _lambert(normal_room[room], ROOM_LIGHT)

    def pixels(samples: torch.Tensor) -> torch.Tensor:  # (B 4 H W, C) -> (B, H, W, C), the mean of each 2x2 block
        return samples.reshape(batch, height, 2, width, 2, -1).mean(dim=(2, 4))

    return pixels(rgb).float(), pixels(on_object[:, None].double())[..., 0] >= 0.5


def turntable_cameras(n_photos: int, rings: int, distance: float) -> tuple[torch.Tensor, torch.Tensor, list[int]]:
    """The photos' cameras in the room's frame, OpenCV c2w (n_photos, 4, 4) (one pose a ring), turn angles (n_photos,)
    (radians) and rings: ring by ring, ``n_photos / rings`` angles evenly spaced, ring r offset by r / rings of a step."""
    if n_photos % rings or n_photos < rings:
        raise ValueError(f"n_photos ({n_photos}) must be a multiple of rings ({rings})")
    per_ring = n_photos // rings
    low, high = ELEVATIONS
    elevations = [math.radians(low + (high - low) * r / (rings - 1) if rings > 1 else (low + high) / 2) for r in range(rings)]
    target = torch.tensor(TARGET, dtype=torch.float64)
    eyes = torch.stack([target + distance * torch.tensor([0.0, -math.cos(e), math.sin(e)], dtype=torch.float64) for e in elevations])
    c2w = look_at(eyes, target)
    ring_of = [photo // per_ring for photo in range(n_photos)]
    turns = torch.tensor([2.0 * math.pi * (photo % per_ring + ring_of[photo] / rings) / per_ring for photo in range(n_photos)], dtype=torch.float64)
    return c2w[ring_of], turns, ring_of


def make_turntable_capture(root: str | Path, n_photos: int = 36, size: int = 192, rings: int = 2, fov_degrees: float = 45.0,
                           distance: float = 3.2, fisheye: tuple[float, float, float, float] | None = None) -> Path:
    """Render the turntable capture into ``root`` (see the module's docstring), through a pinhole or a ``fisheye``
    lens (k1..k4, written as the transforms.json's ``OPENCV_FISHEYE``); returns ``root``."""
    root = Path(root)
    half = torch.tensor(0.5 * math.radians(fov_degrees), dtype=torch.float64)
    # the photo's edge is where the lens puts a ray at half the field of view off axis
    edge = float(torch.tan(half)) if fisheye is None else float(fisheye_radius(half, fisheye))
    focal = 0.5 * size / edge
    K = torch.tensor([[focal, 0.0, size / 2.0], [0.0, focal, size / 2.0], [0.0, 0.0, 1.0]], dtype=torch.float64)
    room_c2w, turns, ring_of = turntable_cameras(n_photos, rings, distance)
    object_c2w = turn_about_z(-turns) @ room_c2w  # the object's frame turns by -turn against the room's
    frames, photos = [], []
    for first in range(0, n_photos, PHOTOS_A_BATCH):
        batch = range(first, min(first + PHOTOS_A_BATCH, n_photos))
        rgb, masks = render_photos(K, room_c2w[batch], turns[batch], size, size, fisheye)
        for photo, image, mask in zip(batch, rgb, masks):
            name = f"turn_{photo:03d}.png"
            write_png(root / "images" / name, image)
            write_png(root / "masks" / name, mask.to(torch.uint8) * 255)
            frames.append({"file_path": f"images/{name}", "mask_path": f"masks/{name}", "transform_matrix": opengl_to_opencv(object_c2w[photo]).tolist()})
            photos.append({"file_path": f"images/{name}", "ring": ring_of[photo], "turn_degrees": math.degrees(turns[photo]),
                           "room_transform_matrix": opengl_to_opencv(room_c2w[photo]).tolist()})
    lens = {"camera_model": "PINHOLE"} if fisheye is None else {"camera_model": "OPENCV_FISHEYE", **dict(zip(FISHEYE_KEYS, fisheye))}
    write_json(root / "transforms.json", {**lens, "fl_x": focal, "fl_y": focal, "cx": size / 2.0, "cy": size / 2.0,
                                          "w": size, "h": size, "frames": frames})
    write_json(root / "turntable.json", {
        "version": VERSION, "n_photos": n_photos, "size": size, "rings": rings, "fov_degrees": fov_degrees, "distance": distance,
        "fisheye": None if fisheye is None else list(fisheye),
        "target": TARGET, "axis": [0.0, 0.0, 1.0], "photos": photos,
    })
    return root


def load_turntable(n_photos: int = 36, size: int = 192, cache_dir: str | Path | None = None, downscale: int = 1,
                   holdout_every: int = 8, **loader_options) -> Scene:
    """The turntable capture in the object's frame, rendered into the cache on first use (``NERF_LIGHTNING_CACHE``,
    default ~/.cache/nerf_lightning) and loaded by the transforms.json loader (``loader_options`` as there)."""
    root = Path(cache_dir or default_cache()) / f"turntable_v{VERSION}_{n_photos}photos_{size}px"
    rendered_once(root, "turntable.json", lambda staging: make_turntable_capture(staging, n_photos=n_photos, size=size))
    return load_transforms(root, downscale=downscale, holdout_every=holdout_every, **loader_options)
