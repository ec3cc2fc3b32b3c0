"""A built-in scene with known geometry, so every command runs offline and depth and meshes can be checked.

Three spheres and two boxes (one a flat plinth) inside radius 1.6 of the origin, lit by one directional
light: ambient + Lambert diffuse + a Blinn-Phong highlight that moves with the viewpoint. The project's own
ray tracer renders it, with exact per-pixel alpha and depth, from cameras spread evenly over a sphere of
radius 4 (a Fibonacci lattice) looking at the origin, and writes it in the Blender layout
(transforms_{train,val,test}.json, RGBA PNGs) plus ``depth_<split>.npy``, so the Blender loader reads it.
Deterministic: the same arguments give the same files.
"""

from __future__ import annotations

import math
import tempfile
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from nerf_lightning.data.choices import PROCEDURAL_MIN_VIEWS
from nerf_lightning.data.formats.blender import load_blender
from nerf_lightning.data.formats.shared import default_cache, rendered_once
from nerf_lightning.data.scene import Scene
from nerf_lightning.geometry.cameras import look_at, opengl_to_opencv
from nerf_lightning.geometry.rays import image_rays
from nerf_lightning.io import write_atomic, write_json, write_png

VERSION = 1  # bump when the scene changes, so caches are rebuilt


@dataclass(frozen=True)
class Sphere:
    centre: tuple[float, float, float]
    radius: float
    albedo: tuple[float, float, float]


@dataclass(frozen=True)
class Box:
    centre: tuple[float, float, float]
    half_size: tuple[float, float, float]
    albedo: tuple[float, float, float]


SPHERES = (
    Sphere((0.45, 0.30, 0.15), 0.50, (0.85, 0.20, 0.15)),
    Sphere((-0.55, -0.40, -0.10), 0.35, (0.15, 0.40, 0.90)),
    Sphere((0.25, -0.70, -0.45), 0.25, (0.95, 0.80, 0.10)),
)
BOXES = (
    Box((-0.25, 0.50, -0.40), (0.40, 0.28, 0.30), (0.20, 0.75, 0.30)),
    Box((0.0, 0.0, -0.80), (1.0, 1.0, 0.10), (0.75, 0.72, 0.68)),
)
LIGHT = (0.4, -0.3, 0.85)  # direction towards the light


def surface_distance(points: torch.Tensor) -> torch.Tensor:
    """Signed distance of (..., 3) points to the scene's surface (negative inside): the exact geometry."""
    distances = []
    for sphere in SPHERES:
        distances.append((points - torch.tensor(sphere.centre, dtype=points.dtype)).norm(dim=-1) - sphere.radius)
    for box in BOXES:
        q = (points - torch.tensor(box.centre, dtype=points.dtype)).abs() - torch.tensor(box.half_size, dtype=points.dtype)
        distances.append(q.clamp(min=0).norm(dim=-1) + q.amax(dim=-1).clamp(max=0))
    return torch.stack(distances).amin(dim=0)


def trace(rays_o: torch.Tensor, rays_d: torch.Tensor) -> dict[str, torch.Tensor]:
    """Intersect (N, 3) rays (unit directions) with the scene in float64.

    Returns ``t`` (N,) distance to the first hit (inf on a miss), ``normal`` (N, 3), ``albedo`` (N, 3).
    """
    o, d = rays_o.double(), rays_d.double()
    count = o.shape[0]
    best_t = torch.full((count,), math.inf, dtype=torch.float64)
    normal = torch.zeros(count, 3, dtype=torch.float64)
    albedo = torch.zeros(count, 3, dtype=torch.float64)

    def keep(t: torch.Tensor, n: torch.Tensor, colour: tuple[float, float, float]) -> None:
        closer = t < best_t
        best_t[closer] = t[closer]
        normal[closer] = n[closer]
        albedo[closer] = torch.tensor(colour, dtype=torch.float64)

    for sphere in SPHERES:
        c = torch.tensor(sphere.centre, dtype=torch.float64)
        oc = o - c
        b = (oc * d).sum(-1)
        disc = b * b - ((oc * oc).sum(-1) - sphere.radius**2)
        root = torch.sqrt(disc.clamp(min=0))
        t = torch.where(-b - root > 1e-9, -b - root, -b + root)
        t = torch.where((disc >= 0) & (t > 1e-9), t, torch.full_like(t, math.inf))
        keep(t, torch.nn.functional.normalize(o + t[:, None].nan_to_num(posinf=0.0) * d - c, dim=-1), sphere.albedo)

    for box in BOXES:
        lo = torch.tensor(box.centre, dtype=torch.float64) - torch.tensor(box.half_size, dtype=torch.float64)
        hi = torch.tensor(box.centre, dtype=torch.float64) + torch.tensor(box.half_size, dtype=torch.float64)
        inv = 1.0 / torch.where(d.abs() < 1e-12, torch.full_like(d, 1e-12), d)
        t0, t1 = (lo - o) * inv, (hi - o) * inv
        t_near, t_far = torch.minimum(t0, t1), torch.maximum(t0, t1)
        entry, axis = t_near.max(dim=-1)
        exit_ = t_far.amin(dim=-1)
        hit = (entry <= exit_) & (entry > 1e-9)
        n = torch.zeros_like(o)
        n[torch.arange(count), axis] = -torch.sign(d[torch.arange(count), axis])
        keep(torch.where(hit, entry, torch.full_like(entry, math.inf)), n, box.albedo)
    return {"t": best_t, "normal": normal, "albedo": albedo}


def shade(hit: dict[str, torch.Tensor], rays_d: torch.Tensor) -> torch.Tensor:
    """Colours (N, 3) of hit points: ambient + Lambert diffuse + a view-dependent Blinn-Phong highlight."""
    light = torch.nn.functional.normalize(torch.tensor(LIGHT, dtype=torch.float64), dim=0)
    n = hit["normal"]
    diffuse = (n @ light).clamp(min=0)[:, None]
    half = torch.nn.functional.normalize(light - rays_d.double(), dim=-1)
    highlight = ((n * half).sum(-1).clamp(min=0) ** 40)[:, None]
    return (hit["albedo"] * (0.3 + 0.7 * diffuse) + 0.45 * highlight).clamp(0, 1)


def camera_positions(count: int, radius: float = 4.0) -> torch.Tensor:
    """``count`` points spread evenly over a sphere (a Fibonacci lattice), poles avoided: (count, 3)."""
    index = torch.arange(count, dtype=torch.float64) + 0.5
    z = 1.0 - 2.0 * index / count
    azimuth = math.pi * (3.0 - math.sqrt(5.0)) * index
    ring = torch.sqrt(1.0 - z * z)
    return radius * torch.stack([ring * torch.cos(azimuth), ring * torch.sin(azimuth), z], dim=-1)


def render_views(c2w: torch.Tensor, K: torch.Tensor, height: int, width: int) -> dict[str, torch.Tensor]:
    """Ray-trace views: (B, 4, 4) OpenCV c2w and (B, 3, 3) K -> ``rgba`` (B, H, W, 4) and ``depth`` (B, H, W)."""
    rays_o, rays_d = image_rays(K.double(), c2w.double(), height, width)  # (B, H*W, 3)
    hit = trace(rays_o.reshape(-1, 3), rays_d.reshape(-1, 3))
    alpha = torch.isfinite(hit["t"]).double()[:, None]
    rgb = shade(hit, rays_d.reshape(-1, 3)) * alpha
    batch = c2w.shape[0]
    return {
        "rgba": torch.cat([rgb, alpha], dim=-1).reshape(batch, height, width, 4).float(),
        "depth": hit["t"].reshape(batch, height, width).float(),
    }


def split_of(index: int) -> str:
    """80 / 10 / 10: views 3, 13, 23, ... are val, 7, 17, 27, ... test, the rest train."""
    return {3: "val", 7: "test"}.get(index % 10, "train")


def make_procedural_scene(root: str | Path, n_views: int = 100, size: int = 100, fov_degrees: float = 50.0) -> Path:
    """Render the procedural scene into ``root`` in the Blender layout; returns ``root``."""
    root = Path(root)
    if n_views < PROCEDURAL_MIN_VIEWS:
        raise ValueError(f"the procedural scene needs at least {PROCEDURAL_MIN_VIEWS} views (for its val and test splits), got {n_views}")
    angle = math.radians(fov_degrees)
    focal = 0.5 * size / math.tan(0.5 * angle)
    c2w = look_at(camera_positions(n_views))  # OpenCV
    K = torch.tensor([[focal, 0.0, size / 2.0], [0.0, focal, size / 2.0], [0.0, 0.0, 1.0]], dtype=torch.float64)
    rendered = render_views(c2w, K.expand(n_views, 3, 3), size, size)

    for split in ("train", "val", "test"):
        indices = [i for i in range(n_views) if split_of(i) == split]
        frames = []
        for i in indices:
            write_png(root / split / f"r_{i}.png", rendered["rgba"][i])
            frames.append({"file_path": f"./{split}/r_{i}", "transform_matrix": opengl_to_opencv(c2w[i]).tolist()})
        write_json(root / f"transforms_{split}.json", {"camera_angle_x": angle, "frames": frames})
        buffer = tempfile.SpooledTemporaryFile()
        np.save(buffer, rendered["depth"][indices].numpy())
        buffer.seek(0)
        write_atomic(root / f"depth_{split}.npy", buffer.read())
    write_json(root / "scene.json", {
        "version": VERSION, "n_views": n_views, "size": size, "fov_degrees": fov_degrees, "camera_radius": 4.0,
        "spheres": [vars(s) for s in SPHERES], "boxes": [vars(b) for b in BOXES], "light": LIGHT,
    })
    return root


def load_procedural(
    n_views: int = 100,
    size: int = 100,
    cache_dir: str | Path | None = None,
    downscale: int = 1,
    max_views: int | None = None,
    near: float = 2.0,
    far: float = 6.0,
    image_cache: str | Path | None = None,
) -> Scene:
    """The procedural scene, rendered into the cache on first use (``NERF_LIGHTNING_CACHE``, default
    ~/.cache/nerf_lightning) and loaded by the Blender loader (``image_cache`` as there)."""
    root = Path(cache_dir or default_cache()) / f"procedural_v{VERSION}_{n_views}views_{size}px"
    rendered_once(root, "scene.json", lambda staging: make_procedural_scene(staging, n_views=n_views, size=size))
    return load_blender(root, downscale=downscale, max_views=max_views, near=near, far=far, image_cache=image_cache)
