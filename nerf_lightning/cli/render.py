"""nerf-render: render from a nerf-train checkpoint into <run>/renders/<time>/ (a model of a scene along a camera path:
GIFs, PNG frames and the path's transforms.json; an image field at any scale)."""

from __future__ import annotations

import logging
from pathlib import Path

import hydra
from omegaconf import DictConfig

import nerf_lightning.config  # noqa: F401 (registers ${run_dir_of:...}, which the config's output_dir uses)
from nerf_lightning.cli.keys import check_render_keys
from nerf_lightning.errors import ensure_writable, report_errors

log = logging.getLogger(__name__)


def render(cfg: DictConfig) -> list[Path]:
    check_render_keys(cfg)
    # imported here, not at the top: a wrong key is answered before torch and Lightning load (seconds)
    from nerf_lightning.checkpoints import load_model
    from nerf_lightning.io import write_png
    from nerf_lightning.models.contract import RendersCamera, RendersImage, implements
    from nerf_lightning.outputs.frames import render_camera_path

    model, info = load_model(cfg.ckpt_path, cfg.device, trust=cfg.trust_checkpoint)
    output_dir = ensure_writable(cfg.output_dir, "output_dir")
    scale = float(cfg.render.scale)
    if implements(model, RendersCamera):
        return render_camera_path(model, info["config"], output_dir, cfg.render.path, cfg.render.frames, scale, cfg.render.fps, cfg.render.depth_colormap,
                                  cfg.render.get("dataparser_transforms"))
    if implements(model, RendersImage):
        image = model.render_image(scale)
        path = write_png(output_dir / f"rgb_scale{scale:g}.png", image)
        log.info("wrote %s (%dx%d)", path, image.shape[1], image.shape[0])
        return [path]
    raise ValueError(f"nerf-render needs a model that renders a camera or an image; {cfg.ckpt_path} holds a {type(model).__name__}, which does neither")


@hydra.main(version_base="1.3", config_path="pkg://nerf_lightning.conf", config_name="render")
@report_errors("nerf-render")
def main(cfg: DictConfig) -> None:
    render(cfg)


if __name__ == "__main__":
    main()
