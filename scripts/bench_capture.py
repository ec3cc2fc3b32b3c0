"""A fast preset on a real capture: trained for a fixed wall time, evaluated on every held-out view, a spiral GIF.

    .venv/bin/python scripts/bench_capture.py --preset fast_llff --root ../shared/data/nerf_llff_data/fern \\
        --minutes 10 --out docs/bench/fern_images8.json -- data.scene.downscale=8
    .venv/bin/python scripts/bench_capture.py --preset fast_unbounded --root ../shared/data/nerfstudio/fox \\
        --minutes 10 --out docs/bench/fox.json

1. Trains ``experiment=<--preset>`` on ``--root`` for ``--minutes`` of training time (validation on one view every
   ``--val-every`` steps, its time not counted: ``StopAtTrainingMinutes``; extra Hydra overrides after ``--``).
2. ``nerf-eval`` on its last checkpoint: PSNR and SSIM on the views of the held-out test split (``--eval-views``
   of them, evenly spaced, or all), timed.
3. ``nerf-render`` of the scene's spiral path (``--frames`` at ``--render-scale``; an LLFF scene's own spiral has
   ``data.scene.render_frames`` frames), timed, and the GIFs' paths.
4. With ``--compare A.json B.json``: one plot (``<out>.png``) of held-out PSNR against training minutes, this run's
   validation curve beside those of earlier runs of this script (another preset on the same scene).
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

from nerf_lightning.outputs.evaluation import evaluate_checkpoint  # noqa: E402
from nerf_lightning.plots import plot_psnr_curves  # noqa: E402
from nerf_lightning.checkpoints import load_model  # noqa: E402
from nerf_lightning.outputs.frames import render_camera_path  # noqa: E402


def plot_comparison(runs: list[dict], path: Path, scene: str) -> Path:
    """Validation PSNR against training minutes of several runs of this script (their JSONs), one line each."""
    curves = {}
    for run in runs:
        label = f"{run['preset']} {' '.join(o for o in run['overrides'] if o.startswith('model.'))}".strip()
        curves[f"{label} ({run['steps']} steps, eval {run['eval']['mean']['psnr']:.2f} dB on {run['eval']['views']} views)"] = (
            [point["seconds"] / 60 for point in run["val_curve"]], [point["psnr"] for point in run["val_curve"]])
    return plot_psnr_curves(curves, path, title=f"{scene}: PSNR of one held-out view, 2 CPU cores", xlabel="training minutes",
                            legend_below=True)


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
    parser.add_argument("--compare", type=Path, nargs="*", default=[], help="earlier JSONs of this script to plot beside this run")
    parser.add_argument("overrides", nargs="*", help="more Hydra overrides, after --")
    args = parser.parse_args()
    if not args.root.exists():
        print(json.dumps({"skipped": f"data not found: {args.root}"}))
        return

    run_dir = (args.run_dir or args.out.with_suffix("")).resolve()
    # steps=None keeps the preset's max_steps and so its learning-rate schedule; the wall time stops it first
    # --minutes of training, validations not counted (a 1008x756 validation view can take a minute on a CPU); the
    # trainer's own max_time, wall time, only as a backstop
    stop = f"+callbacks.stop_at_minutes={{_target_: nerf_lightning.callbacks.StopAtTrainingMinutes, minutes: {args.minutes}}}"
    result = train_preset(args.preset, run_dir, args.root, None, 3 * args.minutes + 30, args.val_every, 1, None, args.seed, False,
                          [*args.overrides, stop])
    ckpt = run_dir / "checkpoints" / "last.ckpt"

    started = time.perf_counter()
    evaluated = evaluate_checkpoint(ckpt, run_dir / "eval", "test", max_views=args.eval_views)
    result["eval"] = {"views": evaluated["views"], "mean": evaluated["mean"], "per_view": evaluated["per_view"],
                      "seconds_per_view": round((time.perf_counter() - started) / evaluated["views"], 2)}

    started = time.perf_counter()
    model, info = load_model(ckpt)
    render_camera_path(model, info["config"], run_dir / "spiral", "spiral", args.frames, args.render_scale)
    result["spiral"] = {"frames": args.frames, "scale": args.render_scale, "seconds_per_frame": round((time.perf_counter() - started) / args.frames, 3),
                        "rgb_gif": str(run_dir / "spiral" / "rgb.gif"), "depth_gif": str(run_dir / "spiral" / "depth.gif")}

    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(result, indent=2) + "\n")
    if args.compare:
        plot_comparison([result, *(json.loads(path.read_text()) for path in args.compare)], args.out.with_suffix(".png"), args.root.name)
    print(json.dumps({k: v for k, v in result.items() if k not in ("val_curve", "overrides")} | {"eval": result["eval"]["mean"]}, indent=2))


if __name__ == "__main__":
    main()
