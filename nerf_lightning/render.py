"""nerf-render: render from a nerf-train checkpoint into <run>/renders/<time>/."""

from __future__ import annotations

import logging
from pathlib import Path

import hydra
from omegaconf import DictConfig, OmegaConf

from nerf_lightning.checkpoints import load_model, run_dir_of
from nerf_lightning.io import write_png

log = logging.getLogger(__name__)

OmegaConf.register_new_resolver("run_dir_of", lambda path: str(run_dir_of(path)), replace=True)


def render_image_field(model, cfg: DictConfig, output_dir: Path) -> list[Path]:
    """An image field renders its image at ``render.scale`` times the fitted size."""
    scale = float(cfg.render.scale)
    image = model.render_image(scale)
    path = write_png(output_dir / f"rgb_scale{scale:g}.png", image)
    log.info("wrote %s (%dx%d)", path, image.shape[1], image.shape[0])
    return [path]


RENDERERS = {"image_field": render_image_field}


def render(cfg: DictConfig) -> list[Path]:
    model, info = load_model(cfg.ckpt_path)
    if info["kind"] not in RENDERERS:
        raise ValueError(f"{cfg.ckpt_path} holds a model of kind '{info['kind']}'; nerf-render knows {sorted(RENDERERS)}")
    return RENDERERS[info["kind"]](model, cfg, Path(cfg.output_dir))


@hydra.main(version_base="1.3", config_path="conf", config_name="render")
def main(cfg: DictConfig) -> None:
    render(cfg)


if __name__ == "__main__":
    main()
