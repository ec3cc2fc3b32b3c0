"""Frame times of the viewer (nerf-view, viewer=live) at each progressive resolution, on a trained lego; JSON out.

    .venv/bin/python scripts/bench_viewer.py --root ../shared/data/nerf_synthetic/lego --minutes 5 \\
        --out docs/bench/viewer_lego_cpu.json

1. Trains ``experiment=<--preset>`` (default ``fast_blender``, lego at 200x200) for ``--minutes`` (or takes ``--ckpt``).
2. Renders, as the viewer does (the model's `render_view` from a browser camera with a 4:3
   canvas), ``--views`` evenly spaced val cameras of lego at each height of ``--heights``, and a 200x200 frame (the
   course's size); the median seconds a frame and rays a second of each, after one warm-up frame.
3. The progressive heights the viewer would choose on this machine (:func:`progressive_heights`, from the measured
   rays a second of the smallest frames, ``moving_frame_s`` 0.25 s as nerf-view's default and 0.1 s as the live
   view's), and the seconds each takes.

Exits 0 with "skipped" when --root is missing.
"""

from __future__ import annotations

import argparse
import json
import math
import platform
import statistics
import sys
import time
from pathlib import Path

import kornia
import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))
from bench_nerf import train_preset  # noqa: E402

from nerf_lightning.checkpoints import load_model  # noqa: E402
from nerf_lightning.data.formats import load_blender  # noqa: E402
from nerf_lightning.data.scene import evenly_spaced  # noqa: E402
from nerf_lightning.devices import resolve_device, synchronize  # noqa: E402

from nerf_lightning.viz.scheduler import browser_camera, progressive_heights  # noqa: E402

ASPECT = 4.0 / 3.0  # a browser canvas


def time_height(model, val, height: int, aspect: float, device) -> dict:
    """Median seconds a frame over the views of ``val``, seen through a browser camera of ``height`` pixels."""
    seconds = []
    for index in range(len(val)):
        c2w = val.c2w[index]
        wxyz = kornia.geometry.conversions.rotation_matrix_to_quaternion(c2w[:3, :3].contiguous()).numpy()
        fov_y = 2.0 * math.atan(0.5 * val.height / float(val.K[index, 1, 1]))
        K, pose, h, w = browser_camera(wxyz, c2w[:3, 3].numpy(), fov_y, aspect, height)
        synchronize(device)
        started = time.perf_counter()
        model.render_view(K, pose, h, w)
        synchronize(device)
        seconds.append(time.perf_counter() - started)
    median = statistics.median(seconds)
    return {"height": h, "width": w, "seconds": round(median, 4), "rays_per_second": round(h * w / median)}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--root", type=Path, default=Path("../shared/data/nerf_synthetic/lego"))
    parser.add_argument("--preset", default="fast_blender")
    parser.add_argument("--minutes", type=float, default=5.0)
    parser.add_argument("--ckpt", type=Path, default=None, help="a trained checkpoint of --root instead of training")
    parser.add_argument("--views", type=int, default=5)
    parser.add_argument("--heights", type=int, nargs="+", default=[32, 64, 128, 256, 512])
    parser.add_argument("--device", default="auto")
    parser.add_argument("--run-dir", type=Path, default=Path("outputs/bench/viewer"))
    parser.add_argument("--out", type=Path, default=Path("docs/bench/viewer_lego_cpu.json"))
    args = parser.parse_args()
    if not args.root.is_dir():
        print(f"skipped: {args.root} not found")
        return
    torch.manual_seed(0)
    training = None
    ckpt = args.ckpt
    if ckpt is None:
        training = train_preset(args.preset, args.run_dir, args.root, steps=None, max_minutes=args.minutes, val_every=1_000_000, val_views=1)
        ckpt = args.run_dir / "checkpoints" / "last.ckpt"
    device = resolve_device(args.device)
    model, info = load_model(ckpt, device)
    val = load_blender(args.root, downscale=4).splits["val"]
    val = val.subset(evenly_spaced(len(val), args.views))

    time_height(model, val.subset([0]), 64, ASPECT, device)  # warm-up
    by_height = [time_height(model, val, height, ASPECT, device) for height in args.heights]
    square = time_height(model, val, 200, 1.0, device)
    rays_per_second = by_height[0]["rays_per_second"]
    schedules = {}
    for moving_frame_s in (0.25, 0.1):
        heights = progressive_heights(rays_per_second, moving_frame_s, ASPECT, max(args.heights))
        schedules[str(moving_frame_s)] = [time_height(model, val, height, ASPECT, device) for height in heights]
    result = {
        "machine": {"platform": platform.platform(), "processor": platform.processor(), "threads": torch.get_num_threads(),
                    "device": str(device) if device.type != "cuda" else torch.cuda.get_device_name(device)},
        "checkpoint": str(ckpt), "global_step": info.get("global_step"), "training": training,
        "views": len(val), "aspect": ASPECT, "by_height": by_height, "square_200": square,
        "progressive": schedules,
    }
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(result, indent=2) + "\n")
    for row in by_height + [square]:
        print(f"{row['width']}x{row['height']}: {row['seconds']:.3f} s, {row['rays_per_second'] / 1000:.0f}k rays/s")
    for budget, rows in schedules.items():
        print(f"moving_frame_s {budget}: " + ", ".join(f"{r['width']}x{r['height']} {r['seconds']:.2f} s" for r in rows))
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
