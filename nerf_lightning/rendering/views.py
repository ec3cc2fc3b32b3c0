"""Rendering whole views of a trained radiance field: what nerf-render, nerf-eval and the viewer show."""

from __future__ import annotations

import logging
from collections.abc import Callable
from pathlib import Path

import imageio.v3 as iio
import matplotlib
import torch
from tqdm import tqdm

from nerf_lightning.checkpoints import load_run_data
from nerf_lightning.data.formats.transforms import transforms_meta
from nerf_lightning.data.scene import Views
from nerf_lightning.geometry.rays import image_rays
from nerf_lightning.io import to_uint8, write_atomic, write_json
from nerf_lightning.video import write_gif, write_mp4

log = logging.getLogger(__name__)


@torch.no_grad()
def render_view(model, K: torch.Tensor, c2w: torch.Tensor, height: int, width: int, chunk_size: int | None = None,
                abort: Callable[[], bool] | None = None) -> dict[str, torch.Tensor] | None:
    """One pinhole view of ``model`` (a :class:`~nerf_lightning.models.RadianceFieldModule`): K (3, 3) and an OpenCV
    c2w (4, 4) -> rgb (H, W, 3), depth (H, W), accumulation (H, W), on the CPU. Rendered on the model's device,
    ``chunk_size`` rays at a time (default: the model's); None when ``abort()`` turns true between two chunks."""
    rays_o, rays_d = image_rays(K[None].to(model.device), c2w[None].to(model.device), height, width)
    out = model.render_chunked(rays_o[0], rays_d[0], chunk_size, abort)
    if out is None:
        return None
    return {key: value.cpu().reshape(height, width, -1).squeeze(-1) for key, value in out.items()}


def render_views(model, views: Views, desc: str = "rendering") -> list[dict[str, torch.Tensor]]:
    """Every view of ``views`` through :func:`render_view`, with a progress bar."""
    return [render_view(model, views.K[index], views.c2w[index], views.height, views.width)
            for index in tqdm(range(len(views)), desc=desc, unit="view")]


def depth_picture(model, depth: torch.Tensor, accumulation: torch.Tensor, colormap: str = "grey") -> torch.Tensor:
    """Depth as the scene space pictures it (near bright, :meth:`SceneSpace.depth_picture
    <nerf_lightning.geometry.space.SceneSpace.depth_picture>`), faded out where nothing is hit: (H, W) grey, or
    (H, W, 3) through a matplotlib colormap such as ``turbo``."""
    grey = model.space.depth_picture(depth) * accumulation
    if colormap == "grey":
        return grey
    if colormap not in matplotlib.colormaps:
        raise ValueError(f"render.depth_colormap must be grey or a matplotlib colormap (turbo, viridis, ...), got '{colormap}'")
    coloured = torch.from_numpy(matplotlib.colormaps[colormap](grey.numpy())[..., :3]).float()
    return coloured * accumulation[..., None]


def write_path_renders(model, views: Views, output_dir: Path, fps: float = 20.0, depth_colormap: str = "grey",
                       desc: str = "rendering") -> list[Path]:
    """Render the frames of a camera path into ``output_dir``: ``frames/rgb_####.png`` and ``depth_####.png``,
    ``rgb.gif`` and ``depth.gif`` (MP4s too with the ``video`` extra), and ``transforms.json``, the path's cameras in
    the capture's coordinates, so that the frames load back as a capture. Returns the files written."""
    frames = render_views(model, views, desc=desc)
    rgb = [to_uint8(frame["rgb"]) for frame in frames]
    depth = [to_uint8(depth_picture(model, frame["depth"], frame["accumulation"], depth_colormap)) for frame in frames]
    written = []
    for index, (colour, distance) in enumerate(zip(rgb, depth)):
        written.append(write_atomic(output_dir / "frames" / f"rgb_{index:04d}.png", iio.imwrite("<bytes>", colour, extension=".png")))
        written.append(write_atomic(output_dir / "frames" / f"depth_{index:04d}.png", iio.imwrite("<bytes>", distance, extension=".png")))
    file_paths = [f"frames/rgb_{index:04d}.png" for index in range(len(frames))]
    world_from_capture = model.space.world_from_capture
    world_from_capture = None if world_from_capture is None else world_from_capture.cpu()
    written.append(write_json(output_dir / "transforms.json", transforms_meta(views, file_paths, world_from_capture)))
    for name, stack in (("rgb", rgb), ("depth", depth)):
        written.append(write_gif(output_dir / f"{name}.gif", stack, fps=fps))
        mp4 = write_mp4(output_dir / f"{name}.mp4", stack, fps=fps)
        if mp4:
            written.append(mp4)
    return written


def render_camera_path(model, config: dict, output_dir: str | Path, path: str = "orbit", frames: int = 60, scale: float = 1.0,
                       fps: float = 20.0, depth_colormap: str = "grey") -> list[Path]:
    """Rebuild the camera ``path`` (test, orbit or spiral; ``frames`` of a generated one) of the run whose resolved
    ``config`` a checkpoint carries, at ``scale`` times its size, and :func:`write_path_renders` it into ``output_dir``."""
    views = load_run_data(config).render_views(path, frames).scaled(scale)
    written = write_path_renders(model, views, Path(output_dir), fps, depth_colormap, desc=f"{path} path")
    log.info("wrote %d %dx%d frames of the %s path to %s", len(views), views.width, views.height, path, output_dir)
    return written
