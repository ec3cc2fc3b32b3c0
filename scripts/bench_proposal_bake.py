"""A proposal-sampler checkpoint's held-out views rendered with its proposal networks as they are and baked into grids
(``model.sampler.bake_resolution``): seconds a view and PSNR / SSIM, one setting after another, JSON out.

    .venv/bin/python scripts/bench_proposal_bake.py <run>/checkpoints/last.ckpt --bake none 128 256 \\
        --out docs/bench/fern_proposal_bake.json

Each setting renders every held-out view (or ``--views`` of them, evenly spaced), ``--downscale`` times smaller (1: full
size), after a small untimed warm-up render; a baked setting bakes first, timed apart (``bake_s``, once a checkpoint:
the bake is kept). Every setting's renders are also compared with the unbaked ones (``psnr_to_unbaked``: how far
baking moves the picture).
"""

from __future__ import annotations

import argparse
import json
import platform
import time
from pathlib import Path

import torch

from nerf_lightning.checkpoints import load_model, load_run_data
from nerf_lightning.data.image_stack import as_float_rgb
from nerf_lightning.data.images import downscale
from nerf_lightning.data.scene import evenly_spaced
from nerf_lightning.metrics import image_metrics



def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("ckpt")
    parser.add_argument("--bake", nargs="+", default=["none", "128", "256"], help="bake resolutions to compare (none: the networks)")
    parser.add_argument("--views", type=int, default=None, help="this many held-out views, evenly spaced (default all)")
    parser.add_argument("--downscale", type=int, default=1, help="render and score the views this many times smaller")
    parser.add_argument("--out", type=Path, required=True)
    args = parser.parse_args()
    torch.manual_seed(0)
    model, info = load_model(args.ckpt)
    if not hasattr(model.sampler, "bake_resolution"):
        raise SystemExit(f"{args.ckpt}: its sampler ({type(model.sampler).__name__}) is not a proposal sampler")
    views = load_run_data(info["config"]).scene.held_out("test")
    if args.views:
        views = views.subset(evenly_spaced(len(views), args.views))
    scaled = views.scaled(1.0 / args.downscale)
    targets = [downscale(as_float_rgb(image), args.downscale) for image in views.images]  # by area, as the loaders do
    height, width = targets[0].shape[:2]  # the floor of a size that is not a multiple, as the loaders' downscale
    result = {"checkpoint": str(Path(args.ckpt).resolve()), "step": info["global_step"], "views": list(views.names),
              "size": [width, height], "chunk_size": model.chunk_size, "threads": torch.get_num_threads(),
              "machine": platform.processor() or platform.machine(), "torch": torch.__version__, "settings": {}}
    unbaked = None
    for setting in args.bake:
        model.sampler.bake_resolution = None if setting == "none" else int(setting)
        model.sampler._bakes.clear()
        bake_s = 0.0
        if model.sampler.bake_resolution is not None:
            started = time.perf_counter()
            with torch.no_grad():
                for level in range(len(model.sampler.proposal_fields)):
                    model.sampler.baked(level)
            bake_s = time.perf_counter() - started
        model.render_view(scaled.K[0], scaled.c2w[0], 64, 64)  # warm-up
        rows, frames = [], []
        for index in range(len(scaled)):
            started = time.perf_counter()
            frame = model.render_view(scaled.K[index], scaled.c2w[index], height, width)
            seconds = time.perf_counter() - started
            metrics = {key: float(value) for key, value in image_metrics(frame["rgb"], targets[index]).items()}
            if unbaked is not None:
                metrics["psnr_to_unbaked"] = float(image_metrics(frame["rgb"], unbaked[index])["psnr"])
            rows.append({"view": views.names[index], "seconds": round(seconds, 2), **metrics})
            frames.append(frame["rgb"])
        if setting == "none":
            unbaked = frames
        mean = {key: sum(row[key] for row in rows) / len(rows) for key in rows[0] if key != "view"}
        result["settings"][setting] = {"bake_s": round(bake_s, 2), "mean": mean, "per_view": rows}
        print(setting, f"bake {bake_s:.1f} s", {key: round(value, 3) for key, value in mean.items()}, flush=True)
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(result, indent=2) + "\n")


if __name__ == "__main__":
    main()
