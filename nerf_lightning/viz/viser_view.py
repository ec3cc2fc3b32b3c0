"""An interactive 3D view in the browser with viser (``pip install -e ".[viz]"``): training cameras as frustums
showing their images, random rays between near and far, their samples, and one camera's own rays."""

from __future__ import annotations

import math
import socket

import numpy as np
import torch

from nerf_lightning.data.image_stack import as_float_rgb
from nerf_lightning.data.scene import Scene, Views
from nerf_lightning.errors import MissingExtraError
from nerf_lightning.geometry.paths import look_at_point
from nerf_lightning.io import to_uint8
from nerf_lightning.viz.rays_sample import RaySample


def require_viser():
    """The viser module; MissingExtraError (one line, naming the extra) when it is not installed."""
    try:
        import viser
        import viser.transforms
    except ImportError as error:
        raise MissingExtraError('the browser view needs viser, an optional extra: pip install -e ".[viz]"') from error
    return viser


def check_port(host: str, port: int, key: str = "port") -> None:
    """ValueError naming ``key`` when nothing can listen on ``host``:``port`` (taken by another program, or not an
    address of this machine). viser itself would move on to the next free port without a word."""
    if not 0 < int(port) < 65536:
        raise ValueError(f"{key}={port} is not a TCP port: expected 1-65535")
    with socket.socket(socket.AF_INET6 if ":" in host else socket.AF_INET) as probe:
        probe.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)  # as the server binds: a closing socket is no conflict
        try:
            probe.bind((host, int(port)))
        except OSError as error:
            taken = error.errno in (98, 48, 10048)  # EADDRINUSE on Linux, macOS, Windows
            why = "is taken by another program (another viewer?)" if taken else f"cannot be opened ({error.strerror or error})"
            raise ValueError(f"port {port} on {host} {why}: choose another with {key}=<port>") from error


def start_server(host: str, port: int, key_prefix: str = ""):
    """A viser server on ``host``:``port``; MissingExtraError without viser, ValueError naming ``<key_prefix>port`` when
    the port is taken."""
    viser = require_viser()
    check_port(host, port, f"{key_prefix}port")
    server = viser.ViserServer(host=host, port=port, verbose=False)
    if server.get_port() != port:  # taken between the check and the bind: viser moved on to another port
        server.stop()
        raise ValueError(f"port {port} on {host} is taken by another program: choose another with {key_prefix}port=<port>")
    return server


def scene_frame(c2w: torch.Tensor) -> tuple[torch.Tensor, float, torch.Tensor]:
    """Where (N, 4, 4) OpenCV cameras look (3,), their mean distance from there, and their images' up (3,) (OpenCV -y)."""
    centre = look_at_point(c2w)
    radius = float((c2w[:, :3, 3] - centre).norm(dim=-1).mean())
    up = torch.nn.functional.normalize(-c2w[:, :3, 1].mean(0), dim=0)
    return centre, radius, up


def add_training_cameras(server, views: Views, radius: float, thumbnail_height: int | None = None, highlight: int | None = None) -> list:
    """One frustum a view under ``/cameras/``, showing its image (shrunk to ``thumbnail_height`` pixels, if given),
    blue, or green for ``highlight``; returns the frustums' handles."""
    viser = require_viser()
    fov = 2.0 * math.atan(0.5 * views.height / float(views.K[0, 1, 1]))  # vertical, radians
    handles = []
    for index in range(len(views)):
        image = None
        if views.images is not None:
            image = as_float_rgb(views.images[index])
            if thumbnail_height is not None and views.height > thumbnail_height:
                size = (thumbnail_height, max(1, round(views.width * thumbnail_height / views.height)))
                image = torch.nn.functional.interpolate(image.permute(2, 0, 1)[None], size=size, mode="area")[0].permute(1, 2, 0)
            image = to_uint8(image)
        c2w = views.c2w[index].double().numpy()
        handles.append(server.scene.add_camera_frustum(
            f"/cameras/{index:03d}",
            fov=fov,
            aspect=views.width / views.height,
            scale=0.1 * radius,
            image=image,
            wxyz=viser.transforms.SO3.from_matrix(c2w[:3, :3]).wxyz,
            position=c2w[:3, 3],
            color=(40, 90, 200) if index != highlight else (30, 160, 60),
        ))
    return handles


def _segments(scene: Scene, sample: RaySample) -> np.ndarray:
    near = sample.rays_o + scene.near * sample.rays_d
    far = sample.rays_o + scene.far * sample.rays_d
    return torch.stack([near, far], dim=1).numpy().astype(np.float32)  # (R, 2, 3)


def serve_scene(scene: Scene, all_rays: RaySample, one_camera: RaySample, camera: int, host: str = "127.0.0.1", port: int = 8080):
    """Start a viser server showing the scene; returns the server (``server.stop()`` ends it)."""
    server = start_server(host, port, "viz.")
    train = scene.train
    centre, radius, up = scene_frame(train.c2w)
    server.scene.set_up_direction(up.double().numpy())
    # start outside the ring of cameras, looking at where they look
    outside = torch.nn.functional.normalize(train.c2w[0, :3, 3] - centre, dim=0) + 0.6 * up
    server.initial_camera.look_at = centre.double().numpy()
    server.initial_camera.position = (centre + 2.2 * radius * torch.nn.functional.normalize(outside, dim=0)).double().numpy()
    add_training_cameras(server, train, radius, highlight=camera)
    server.scene.add_line_segments("/rays/random", points=_segments(scene, all_rays), colors=(220, 50, 40), thickness=0.004 * radius)
    server.scene.add_point_cloud("/samples/random", points=all_rays.points.reshape(-1, 3).numpy(), colors=(20, 20, 20), point_size=0.01 * radius)
    server.scene.add_line_segments(f"/rays/camera_{camera}", points=_segments(scene, one_camera), colors=(30, 160, 60), thickness=0.004 * radius)
    server.scene.add_point_cloud(f"/samples/camera_{camera}", points=one_camera.points.reshape(-1, 3).numpy(), colors=(30, 120, 40), point_size=0.01 * radius)
    return server
