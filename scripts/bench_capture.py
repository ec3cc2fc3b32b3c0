"""A fast preset on a real capture: trained for a fixed wall time, evaluated on every held-out view, a spiral GIF.

    .venv/bin/python scripts/bench_capture.py --preset fast_llff --root ../shared/data/nerf_llff_data/fern \\
        --minutes 10 --out docs/bench/fern_images8.json -- data.scene.downscale=8
    .venv/bin/python scripts/bench_capture.py --preset fast_unbounded --root ../shared/data/nerfstudio/fox \\
        --minutes 10 --out docs/bench/fox.json

1. Trains ``experiment=<--preset>`` on ``--root`` for ``--minutes`` of wall time (validation on one view every
   ``--val-every`` steps, its time left out of the training seconds; extra Hydra overrides after ``--``).
2. ``nerf-eval`` on its last checkpoint: PSNR and SSIM on the views of the held-out test split (``--eval-views``
   of them, evenly spaced, or all), timed.
3. ``nerf-render`` of the scene's spiral path (``--frames`` at ``--render-scale``; an LLFF scene's own spiral has
   ``data.scene.render_frames`` frames), timed, and the GIFs' paths.
Writes the JSON (and the run folder beside it, or ``--run-dir``). Exits 0 with "skipped" when --root is missing.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
from bench_nerf import train_preset  # noqa: E402

from nerf_lightning.evaluation import evaluate_checkpoint  # noqa: E402
from nerf_lightning.checkpoints import load_model  # noqa: E402
from nerf_lightning.rendering.views import render_camera_path  # noqa: E402


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--preset", required=True)
    parser.add_argument("--root", type=Path, required=True)
    parser.add_argument("--minutes", type=float, default=10.0)
    parser.add_argument("--val-every", type=int, default=500)
    parser.add_argument("--frames", type=int, default=60, help="frames of the spiral GIF")
    parser.add_argument("--render-scale", type=float, default=1.0, help="render.scale of the spiral GIF")
    parser.add_argument("--eval-views", type=int, default=None, help="evaluate this many held-out views, evenly spaced (default all)")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--run-dir", type=Path, default=None)
    parser.add_argument("--out", type=Path, required=True)
    parser.add_argument("overrides", nargs="*", help="more Hydra overrides, after --")
    args = parser.parse_args()
    if not args.root.exists():
        print(json.dumps({"skipped": f"data not found: {args.root}"}))
        return

    run_dir = (args.run_dir or args.out.with_suffix("")).resolve()
    # steps=None keeps the preset's max_steps and so its learning-rate schedule; the wall time stops it first
    result = train_preset(args.preset, run_dir, args.root, None, args.minutes, args.val_every, 1, None, args.seed, False, args.overrides)
    ckpt = run_dir / "checkpoints" / "last.ckpt"

    started = time.perf_counter()
    evaluated = evaluate_checkpoint(ckpt, run_dir / "eval", "test", max_views=args.eval_views)
    result["eval"] = {"views": evaluated["views"], "mean": evaluated["mean"], "per_view": evaluated["per_view"],
                      "seconds_per_view": round((time.perf_counter() - started) / evaluated["views"], 2)}

    started = time.perf_counter()
    model, info = load_model(ckpt, kind="radiance_field")
    render_camera_path(model, info["config"], run_dir / "spiral", "spiral", args.frames, args.render_scale)
    result["spiral"] = {"frames": args.frames, "scale": args.render_scale, "seconds_per_frame": round((time.perf_counter() - started) / args.frames, 3),
                        "rgb_gif": str(run_dir / "spiral" / "rgb.gif"), "depth_gif": str(run_dir / "spiral" / "depth.gif")}

    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(result, indent=2) + "\n")
    print(json.dumps({k: v for k, v in result.items() if k not in ("val_curve", "overrides")} | {"eval": result["eval"]["mean"]}, indent=2))


if __name__ == "__main__":
    main()
