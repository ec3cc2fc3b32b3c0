"""One held-out view of a checkpoint as a picture a reader can judge a score by: the photo, the render and their
difference (x4), side by side, with the view's PSNR, SSIM and LPIPS written under them (scored by ``nerf-eval``'s
own per-view scoring, :func:`~nerf_lightning.outputs.evaluation.evaluate_views`).

    python scripts/heldout_frame.py CKPT OUT.png [--view r_15.png] [--lpips-weights ../shared/data/lpips]

Without ``--view`` the view is the one of median LPIPS over the held-out split (a typical frame, not the best).
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np
import torch
from PIL import Image, ImageDraw

from nerf_lightning.checkpoints import load_model
from nerf_lightning.data.scene_data import view_batch
from nerf_lightning.outputs.evaluation import evaluate_views, views_to_evaluate
from nerf_lightning.outputs.frames import render_frame
from nerf_lightning.outputs.lpips import load_lpips


def picture(photo: torch.Tensor, render: torch.Tensor, caption: str) -> Image.Image:
    """Photo | render | |render - photo| x 4 over a caption line: one RGB image."""
    difference = ((render - photo).abs() * 4.0).clamp(0.0, 1.0)
    row = torch.cat([photo, render, difference], dim=1)
    image = Image.fromarray((row.numpy() * 255.0 + 0.5).astype(np.uint8))
    canvas = Image.new("RGB", (image.width, image.height + 18), "white")
    canvas.paste(image, (0, 0))
    ImageDraw.Draw(canvas).text((4, image.height + 3), caption, fill="black")
    return canvas


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("ckpt")
    parser.add_argument("out")
    parser.add_argument("--view", help="the held-out view's file name (default: the one of median LPIPS)")
    parser.add_argument("--split", default="test")
    parser.add_argument("--lpips-weights", help="a file or folder of LPIPS's weights (as eval.lpips_weights)")
    args = parser.parse_args()
    model, info = load_model(args.ckpt)
    lpips, where = load_lpips("auto", args.lpips_weights)
    if lpips is None:
        raise SystemExit(where)
    views, masks, background = views_to_evaluate(model, info["config"], args.split)
    if args.view is not None:
        if args.view not in views.names:
            raise SystemExit(f"--view {args.view}: not a held-out view of {args.ckpt} (its views: {', '.join(views.names)})")
        views = views.subset([views.names.index(args.view)])
    # each view scored as nerf-eval scores it; without --view, all of them, to find the median
    with torch.no_grad():
        rows = evaluate_views(model, views, None, masks, background, lpips)
        index = sorted(range(len(rows)), key=lambda i: rows[i]["lpips"])[len(rows) // 2]
        render = render_frame(model, views, index)["rgb"].clamp(0.0, 1.0)
    photo, scores = view_batch(views, index, masks, background)["image"], rows[index]
    caption = f"{views.names[index]}: photo | render | difference x4   PSNR {scores['psnr']:.2f}  SSIM {scores['ssim']:.3f}  LPIPS {scores['lpips']:.4f}"
    Path(args.out).parent.mkdir(parents=True, exist_ok=True)
    picture(photo, render, caption).save(args.out)
    print(caption, "->", args.out)


if __name__ == "__main__":
    main()
