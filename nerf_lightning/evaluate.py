"""nerf-eval: render every held-out view of a radiance field's scene; eval.json with PSNR, SSIM and depth error.

``root=<transforms.json>`` evaluates on views captured separately instead: a second file of the same capture
(instant-ngp / nerfstudio / Blender layout), loaded into the trained scene's world with the similarity the
training scene was normalised by (``world_from_capture``), its images downscaled and composited as in training.
"""

from __future__ import annotations

import logging
from pathlib import Path

import hydra
import kornia
import torch
from omegaconf import DictConfig

from nerf_lightning.checkpoints import load_model, load_run_data
from nerf_lightning.data.formats.transforms import load_transforms
from nerf_lightning.data.image_stack import as_float_rgb
from nerf_lightning.data.scene import Scene, Views, evenly_spaced
from nerf_lightning.errors import ensure_writable, report_errors
from nerf_lightning.io import write_json, write_png
from nerf_lightning.render import render_views

log = logging.getLogger(__name__)


def second_capture(model, config: dict, root: str) -> Scene:
    """Another ``transforms.json`` of the trained capture, in the trained scene's world: every frame with an image
    in ``train`` (``holdout_every=0``) or in the splits the file names; downscale and background as in training."""
    scene_cfg = config["data"]["scene"]
    world_from_capture = model.world_from_capture if model.world_from_capture is not None else torch.eye(4)
    return load_transforms(root, downscale=int(scene_cfg.get("downscale", 1)), holdout_every=0, world_from_capture=world_from_capture,
                           background=tuple(scene_cfg.get("background") or (0.0, 0.0, 0.0)))


def views_to_evaluate(model, config: dict, cfg: DictConfig) -> Views:
    """The held-out views of the run's scene, or those of ``cfg.root`` (its ``cfg.split`` if it names one, else all)."""
    if not cfg.get("root"):
        return load_run_data(config).scene.held_out(cfg.split)
    scene = second_capture(model, config, cfg.root)
    return scene.splits[cfg.split] if cfg.split in scene.splits else scene.train


def evaluate(cfg: DictConfig) -> dict:
    model, info = load_model(cfg.ckpt_path, kind="radiance_field", command="nerf-eval")
    ensure_writable(cfg.output_dir, "output_dir")
    views = views_to_evaluate(model, info["config"], cfg)
    if cfg.max_views:
        views = views.subset(evenly_spaced(len(views), cfg.max_views))
    output_dir = Path(cfg.output_dir)
    rendered = render_views(model, views, desc=f"evaluating {len(views)} views")
    per_view = []
    for index, frame in enumerate(rendered):
        target = as_float_rgb(views.images[index])
        row = {
            "view": views.names[index],
            "psnr": float(kornia.metrics.psnr(frame["rgb"], target, max_val=1.0)),
            "ssim": float(kornia.metrics.ssim(frame["rgb"].permute(2, 0, 1)[None], target.permute(2, 0, 1)[None], window_size=11).mean()),
        }
        if views.depth is not None:
            surface = torch.isfinite(views.depth[index])
            row["depth_error"] = float((frame["depth"][surface] - views.depth[index][surface]).abs().mean())
        per_view.append(row)
        stem = Path(views.names[index]).stem
        write_png(output_dir / "images" / f"{stem}_rgb.png", frame["rgb"])
        write_png(output_dir / "images" / f"{stem}_depth.png", model.depth_image(frame["depth"]) * frame["accumulation"])
    keys = [key for key in ("psnr", "ssim", "depth_error") if key in per_view[0]]
    mean = {key: sum(row[key] for row in per_view) / len(per_view) for key in keys}
    result = {"checkpoint": str(Path(cfg.ckpt_path).resolve()), "step": info["global_step"], "split": cfg.split,
              "scene": str(Path(cfg.root).resolve()) if cfg.get("root") else "the run's own",
              "views": len(per_view), "mean": mean, "per_view": per_view}
    write_json(output_dir / "eval.json", result)
    log.info("%d views: %s -> %s", len(per_view), ", ".join(f"{k} {v:.4f}" for k, v in mean.items()), output_dir / "eval.json")
    return result


@hydra.main(version_base="1.3", config_path="conf", config_name="eval")
@report_errors("nerf-eval")
def main(cfg: DictConfig) -> None:
    evaluate(cfg)


if __name__ == "__main__":
    main()
