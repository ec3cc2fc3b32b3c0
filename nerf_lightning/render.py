"""nerf-render: render from a nerf-train checkpoint into <run>/renders/<time>/."""

from __future__ import annotations

import logging
from pathlib import Path

import hydra
import matplotlib
import torch
from omegaconf import DictConfig
from tqdm import tqdm

from nerf_lightning.checkpoints import load_model, load_run_data
from nerf_lightning.data.formats.transforms import transforms_meta
from nerf_lightning.data.scene import Views
from nerf_lightning.errors import ensure_writable, report_errors
from nerf_lightning.geometry.rays import image_rays
from nerf_lightning.io import to_uint8, write_json, write_png
from nerf_lightning.video import write_gif, write_mp4

log = logging.getLogger(__name__)


def render_image_field(model, cfg: DictConfig, output_dir: Path, config: dict) -> list[Path]:
    """An image field renders its image at ``render.scale`` times the fitted size."""
    scale = float(cfg.render.scale)
    image = model.render_image(scale)
    path = write_png(output_dir / f"rgb_scale{scale:g}.png", image)
    log.info("wrote %s (%dx%d)", path, image.shape[1], image.shape[0])
    return [path]


def scaled(views: Views, scale: float) -> Views:
    """The same cameras rendering ``scale`` times as many pixels a side."""
    if scale == 1.0:
        return views
    K = views.K.clone()
    K[:, :2] *= scale
    return Views(K=K, c2w=views.c2w, height=round(views.height * scale), width=round(views.width * scale), names=views.names)


def depth_picture(model, depth: torch.Tensor, accumulation: torch.Tensor, colormap: str) -> torch.Tensor:
    """Depth normalised to near..far (near bright) and faded out where nothing is hit: (H, W) grey or (H, W, 3)."""
    grey = model.depth_image(depth) * accumulation
    if colormap == "grey":
        return grey
    coloured = torch.from_numpy(matplotlib.colormaps[colormap](grey.numpy())[..., :3]).float()
    return coloured * accumulation[..., None]


@torch.no_grad()
def render_views(model, views: Views, desc: str = "rendering") -> list[dict[str, torch.Tensor]]:
    """Render every view: rgb (H, W, 3), depth (H, W), accumulation (H, W), with a progress bar."""
    frames = []
    for index in tqdm(range(len(views)), desc=desc, unit="view"):
        rays_o, rays_d = image_rays(views.K[index : index + 1], views.c2w[index : index + 1], views.height, views.width)
        out = model.render_chunked(rays_o[0].to(model.device), rays_d[0].to(model.device))
        frames.append({key: value.cpu().reshape(views.height, views.width, -1).squeeze(-1) for key, value in out.items()})
    return frames


def render_radiance_field(model, cfg: DictConfig, output_dir: Path, config: dict) -> list[Path]:
    """A radiance field renders the frames of a camera path: rgb.gif, depth.gif (and .mp4), PNG frames, and
    transforms.json: the path's cameras in the capture's coordinates, so the frames load back as a capture."""
    datamodule = load_run_data(config)
    views = datamodule.render_views(cfg.render.path, cfg.render.frames)
    views = scaled(views, float(cfg.render.scale))
    frames = render_views(model, views, desc=f"{cfg.render.path} path")
    rgb = [to_uint8(frame["rgb"]) for frame in frames]
    depth = [to_uint8(depth_picture(model, frame["depth"], frame["accumulation"], cfg.render.depth_colormap)) for frame in frames]
    written = []
    for index, (colour, distance) in enumerate(zip(frames, depth)):
        written.append(write_png(output_dir / "frames" / f"rgb_{index:04d}.png", colour["rgb"]))
        written.append(write_png(output_dir / "frames" / f"depth_{index:04d}.png", torch.from_numpy(distance).float() / 255.0))
    file_paths = [f"frames/rgb_{index:04d}.png" for index in range(len(frames))]
    written.append(write_json(output_dir / "transforms.json", transforms_meta(views, file_paths, model.world_from_capture)))
    for name, stack in (("rgb", rgb), ("depth", depth)):
        written.append(write_gif(output_dir / f"{name}.gif", stack, fps=cfg.render.fps))
        mp4 = write_mp4(output_dir / f"{name}.mp4", stack, fps=cfg.render.fps)
        if mp4:
            written.append(mp4)
    log.info("wrote %d %dx%d frames of the %s path to %s", len(frames), views.width, views.height, cfg.render.path, output_dir)
    return written


RENDERERS = {"image_field": render_image_field, "radiance_field": render_radiance_field}


def render(cfg: DictConfig) -> list[Path]:
    model, info = load_model(cfg.ckpt_path)
    ensure_writable(cfg.output_dir, "output_dir")
    if info["kind"] not in RENDERERS:
        raise ValueError(f"{cfg.ckpt_path} holds a model of kind '{info['kind']}'; nerf-render knows {sorted(RENDERERS)}")
    return RENDERERS[info["kind"]](model, cfg, Path(cfg.output_dir), info["config"])


@hydra.main(version_base="1.3", config_path="conf", config_name="render")
@report_errors("nerf-render")
def main(cfg: DictConfig) -> None:
    render(cfg)


if __name__ == "__main__":
    main()
