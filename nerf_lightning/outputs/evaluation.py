"""Evaluating a trained model (any that renders a camera) on held-out views: PSNR, SSIM, LPIPS (where its weights
can be had: :mod:`nerf_lightning.outputs.lpips`) and depth error per view and on average; and the same colour
scores after each render's colours are mapped to its photo's by the affine map that fits them best
(:func:`~nerf_lightning.metrics.colour_correct`): ``cc_psnr``, ``cc_ssim``, ``cc_lpips`` (and ``cc_psnr_masked``),
named as gsplat names them. The raw scores are the headline; the ``cc_`` ones say what is left once a held-out
photo's exposure and white balance, which no training photo tells, are taken out.

``root=<transforms.json>`` evaluates on views captured separately instead: a second file of the same capture
(instant-ngp / nerfstudio / Blender layout), loaded into the trained scene's world with the similarity the
training scene was normalised by (``world_from_capture``), its images downscaled and composited as in training.
"""

from __future__ import annotations

import logging
import statistics
import time
from pathlib import Path
from typing import Any

import torch
from tqdm import tqdm

from nerf_lightning.checkpoints import load_model, load_run_data
from nerf_lightning.data.formats.transforms import load_transforms
from nerf_lightning.data.masks import resolve_mode
from nerf_lightning.data.scene import Scene, Views, evenly_spaced
from nerf_lightning.data.scene_data import view_batch
from nerf_lightning.io import write_json, write_png
from nerf_lightning.outputs.lpips import LPIPS, load_lpips
from nerf_lightning.metrics import colour_correct, image_metrics
from nerf_lightning.models.contract import RendersCamera, require
from nerf_lightning.outputs.frames import render_frame

log = logging.getLogger(__name__)

# eval.json's "masks": what "psnr" and "ssim" cover (the results table's PSNR and SSIM) and what "_masked" ones do
MASKS_SAID = {
    None: {"mode": None, "psnr": "the whole image"},
    "exclude": {"mode": "exclude", "psnr": "the whole image, the photo as it is",
                "psnr_masked": "the masked pixels alone (what training learnt from)"},
    "background": {"mode": "background", "psnr": "the whole image, the photo's masked pixels over the background colour",
                   "psnr_masked": "the masked pixels alone (the object)"},
}


def second_capture(model: RendersCamera, config: dict, root: str | Path) -> Scene:
    """Another ``transforms.json`` of the trained capture, in the trained scene's world: every frame with an image
    in ``train`` (``holdout_every=0``) or in the splits the file names; downscale and background as in training."""
    scene_cfg = config["data"]["scene"]
    world_from_capture = model.space.world_from_capture
    world_from_capture = torch.eye(4) if world_from_capture is None else world_from_capture.cpu()
    return load_transforms(root, downscale=int(scene_cfg.get("downscale", 1)), holdout_every=0, world_from_capture=world_from_capture,
                           background=tuple(scene_cfg.get("background") or (0.0, 0.0, 0.0)))


def views_to_evaluate(model: RendersCamera, config: dict, split: str = "test", root: str | Path | None = None) -> tuple[Views, str | None, torch.Tensor]:
    """The held-out views of the run's scene (``split``, else the other held-out split), or those of ``root`` (its
    ``split`` if it names one, else all); the masks mode training used (:mod:`~nerf_lightning.data.masks`) and the
    scene's background colour, with which they are scored."""
    if not root:
        data = load_run_data(config, model)
        return data.scene.held_out(split), data.mask_mode, data.scene.background
    scene = second_capture(model, config, root)
    mode = resolve_mode(config["data"].get("masks"), scene.train.masks is not None, scene.source)
    return scene.splits[split] if split in scene.splits else scene.train, mode, scene.background


def evaluate_views(model: RendersCamera, views: Views, output_dir: Path | None = None, masks: str | None = None,
                   background: torch.Tensor | None = None, lpips: LPIPS | None = None) -> list[dict[str, Any]]:
    """Render ``views`` (with images) and score each with :func:`~nerf_lightning.metrics.image_metrics`, timing each
    render (``seconds``: the first view's includes any one-off compilation); with
    ``output_dir``, the renders go to ``images/<view>_rgb.png`` and ``_depth.png`` there. With a ``masks`` mode and
    masks, each view is scored over the whole image (with ``background``, the photo composited onto ``background``
    outside its mask, as training saw it) and over its mask alone (``psnr_masked``, ``ssim_masked``). With ``lpips``,
    each view's ``lpips`` too (over the whole image). Each colour score again as ``cc_<name>``, of the render mapped to
    the photo's colours (:func:`~nerf_lightning.metrics.colour_correct`, fitted over the whole image; with masks in
    ``background`` mode, over the mask, which alone it changes)."""
    rows = []
    for index in tqdm(range(len(views)), desc=f"evaluating {len(views)} views", unit="view"):
        started = time.perf_counter()
        frame = render_frame(model, views, index)  # on the CPU when it returns: the device has finished
        seconds = time.perf_counter() - started
        true_depth = views.depth[index] if views.depth is not None else None
        batch = view_batch(views, index, masks, background)  # the target as validation sees it
        target, mask = batch["image"], batch.get("object_mask")
        metrics = image_metrics(frame["rgb"], target, frame["depth"] if true_depth is not None else None, true_depth, mask)
        # with data.masks=background the photo's background is the loader's colour: the map fitted to the object alone
        corrected = colour_correct(frame["rgb"].clamp(0.0, 1.0), target, mask if masks == "background" else None)
        metrics.update({f"cc_{key}": value for key, value in image_metrics(corrected, target, mask=mask).items()})
        if lpips is not None:
            metrics["lpips"] = lpips(frame["rgb"].clamp(0.0, 1.0), target)
            metrics["cc_lpips"] = lpips(corrected, target)
        rows.append({"view": views.names[index], **{key: float(value) for key, value in metrics.items()}, "seconds": round(seconds, 4)})
        if output_dir is not None:
            stem = Path(views.names[index]).stem
            write_png(output_dir / "images" / f"{stem}_rgb.png", frame["rgb"])
            write_png(output_dir / "images" / f"{stem}_depth.png", model.space.depth_picture(frame["depth"], frame["accumulation"]))
    return rows


def mean_metrics(rows: list[dict[str, Any]]) -> dict[str, float]:
    """The mean of each metric over the views (depth error over the views where it is defined)."""
    names = ("psnr", "ssim", "lpips", "psnr_masked", "ssim_masked")
    keys = [key for key in (*names, "depth_error", *(f"cc_{name}" for name in names)) if any(key in row for row in rows)]
    mean = {}
    for key in keys:
        values = [row[key] for row in rows if key in row and row[key] == row[key]]  # NaN: a view with no surface
        if values:
            mean[key] = sum(values) / len(values)
    return mean


def evaluate_checkpoint(ckpt_path: str | Path, output_dir: str | Path, split: str = "test", root: str | Path | None = None,
                        max_views: int | None = None, device: str = "cpu", trust: bool = False, lpips: str = "auto",
                        lpips_weights: str | Path | None = None) -> dict[str, Any]:
    """Evaluate the model of a checkpoint (any that renders a camera; see :func:`views_to_evaluate`); writes
    ``eval.json`` and the renders into ``output_dir`` and returns what eval.json holds. Rendered on ``device`` (auto,
    cpu, cuda, mps); ``trust``: see :func:`~nerf_lightning.checkpoints.read_checkpoint`; ``lpips`` and
    ``lpips_weights``: see :func:`~nerf_lightning.outputs.lpips.load_lpips` (without weights, eval.json says why LPIPS is
    absent, and the log says it once)."""
    network, lpips_said = load_lpips(lpips, lpips_weights)  # before the model: a wrong weights file is said at once
    if network is None and lpips != "off":
        log.warning("%s", lpips_said)
    model, info = load_model(ckpt_path, device, trust=trust)
    if network is not None:
        network.to(model.device)
    require(model, RendersCamera, "nerf-eval", "a model that renders a camera")
    output_dir = Path(output_dir)
    views, masks, background = views_to_evaluate(model, info["config"], split, root)
    if max_views:
        views = views.subset(evenly_spaced(len(views), max_views))
    rows = evaluate_views(model, views, output_dir, masks, background, network)
    result = {"checkpoint": str(Path(ckpt_path).resolve()), "step": info["global_step"], "split": split,
              "scene": str(Path(root).resolve()) if root else "the run's own", "views": len(rows), "frame_size": [views.height, views.width],
              "mean": mean_metrics(rows), "masks": MASKS_SAID.get(masks, MASKS_SAID[None]),
              "lpips": {"network": "LPIPS 0.1, AlexNet", "weights": lpips_said} if network is not None else {"skipped": lpips_said},
              "seconds_per_frame": statistics.median(row["seconds"] for row in rows) if rows else None,
              "device": str(model.device), "per_view": rows}
    write_json(output_dir / "eval.json", result)
    log.info("%d views: %s -> %s", len(rows), ", ".join(f"{k} {v:.4f}" for k, v in result["mean"].items()), output_dir / "eval.json")
    return result
