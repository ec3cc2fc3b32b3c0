"""Frames of a trained model: views rendered through the model contract, depth pictured, camera paths written as
PNG frames, GIFs (MP4s with the ``video`` extra) and the path's ``transforms.json``."""

from __future__ import annotations

import logging
from pathlib import Path

import imageio.v3 as iio
import matplotlib
import torch
from tqdm import tqdm

from nerf_lightning.checkpoints import load_run_data
from nerf_lightning.data.choices import is_camera_path_file
from nerf_lightning.data.formats.camera_path import read_camera_path
from nerf_lightning.data.formats.transforms import transforms_meta
from nerf_lightning.data.scene import Views
from nerf_lightning.geometry.space import SceneSpace
from nerf_lightning.io import to_uint8, write_atomic, write_json
from nerf_lightning.models.contract import RendersCamera
from nerf_lightning.outputs.video import write_gif, write_mp4

log = logging.getLogger(__name__)


def render_frame(model: RendersCamera, views: Views, index: int) -> dict[str, torch.Tensor]:
    """View ``index`` of ``views`` through ``model.render_view``: rgb (H, W, 3), depth (H, W), accumulation (H, W)
    on the CPU, float32."""
    frame = model.render_view(views.K[index], views.c2w[index], views.height, views.width)
    return {key: value.detach().float().cpu() for key, value in frame.items()}


def render_frames(model: RendersCamera, views: Views, desc: str = "rendering") -> list[dict[str, torch.Tensor]]:
    """Every view of ``views`` through :func:`render_frame`, with a progress bar."""
    return [render_frame(model, views, index) for index in tqdm(range(len(views)), desc=desc, unit="view")]


def depth_picture(space: SceneSpace, depth: torch.Tensor, accumulation: torch.Tensor, colormap: str = "grey") -> torch.Tensor:
    """Depth as the scene space pictures it (near bright, :meth:`SceneSpace.depth_picture
    <nerf_lightning.geometry.space.SceneSpace.depth_picture>`), faded out where nothing is hit: (H, W) grey, or
    (H, W, 3) through a matplotlib colormap such as ``turbo``."""
    if colormap == "grey":
        return space.depth_picture(depth, accumulation)
    if colormap not in matplotlib.colormaps:
        raise ValueError(f"render.depth_colormap must be grey or a matplotlib colormap (turbo, viridis, ...), got '{colormap}'")
    # the colour of the depth itself, then faded: a half-transparent pixel keeps its depth's hue
    coloured = torch.from_numpy(matplotlib.colormaps[colormap](space.depth_picture(depth).numpy())[..., :3]).float()
    return coloured * accumulation[..., None]


def write_path_renders(model: RendersCamera, views: Views, output_dir: Path, fps: float = 20.0, depth_colormap: str = "grey",
                       desc: str = "rendering") -> list[Path]:
    """Render the frames of a camera path into ``output_dir``: ``frames/rgb_####.png`` and ``depth_####.png``,
    ``rgb.gif`` and ``depth.gif`` (MP4s too with the ``video`` extra), and ``transforms.json``, the path's cameras in
    the capture's coordinates, so that the frames load back as a capture. Returns the files written."""
    output_dir = Path(output_dir)
    frames = render_frames(model, views, desc=desc)
    rgb = [to_uint8(frame["rgb"]) for frame in frames]
    depth = [to_uint8(depth_picture(model.space, frame["depth"], frame["accumulation"], depth_colormap)) for frame in frames]
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


def render_camera_path(model: RendersCamera, config: dict, output_dir: str | Path, path: str = "orbit", frames: int = 60, scale: float = 1.0,
                       fps: float = 20.0, depth_colormap: str = "grey", dataparser_transforms: str | Path | None = None) -> list[Path]:
    """Rebuild the camera ``path`` (test, orbit or spiral; ``frames`` of a generated one) of the run whose resolved
    ``config`` a checkpoint carries, or read a camera path file (:mod:`~nerf_lightning.data.formats.camera_path`:
    at its size and frames a second; ``dataparser_transforms`` for one in nerfstudio's normalised world), at ``scale``
    times its size, and :func:`write_path_renders` it into ``output_dir``."""
    if is_camera_path_file(path):
        world_from_capture = model.space.world_from_capture
        world_from_capture = None if world_from_capture is None else world_from_capture.cpu()
        views, file_fps = read_camera_path(path, world_from_capture, dataparser_transforms)
        fps, name = file_fps or fps, Path(path).name
    else:
        views, name = load_run_data(config, model).render_views(path, frames), f"{path} path"
    views = views.scaled(scale)
    written = write_path_renders(model, views, Path(output_dir), fps, depth_colormap, desc=name)
    log.info("wrote %d %dx%d frames of %s to %s", len(views), views.width, views.height, name, output_dir)
    return written
