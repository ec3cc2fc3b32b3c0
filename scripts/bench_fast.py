"""The fast path on a Blender scene: PSNR against time, samples a ray, rays a second, frame time; JSON and a markdown row.

    .venv/bin/python scripts/bench_fast.py --root ../shared/data/nerf_synthetic/lego --minutes 10 \\
        --paper-curve docs/bench/nerf_lego_paper_1024.json --grid-minutes 45 --out docs/bench/fast_lego.json

1. Trains ``experiment=<--preset>`` (default ``fast_blender``) for ``--minutes`` of wall time (validation on ``--val-views`` views every
   ``--val-every`` steps; its time is left out of the training seconds), then, from the last checkpoint, on
   ``--eval-views`` evenly spaced views of the val split: PSNR and SSIM; seconds to render one frame; samples a ray
   three ways: what plain stepping at the marcher's step would evaluate inside near..far and the box, what the
   occupancy grid lists, and what the field is evaluated at after early ray termination.
2. With ``--grid-minutes`` > 0: the paper's MLP with the occupancy grid (``experiment=nerf_blender_grid``) until
   ``--grid-target`` dB or that many minutes; its time to the target is compared with the paper MLP's run without
   the grid, read from ``--paper-curve`` (a ``scripts/bench_nerf.py`` JSON of the same recipe on the same machine).
3. One plot of validation PSNR against training minutes for all of them, beside the JSON.

``--report-only`` trains nothing and redoes step 3 and the comparison from an existing ``--out`` (after the
no-grid run in ``--paper-curve`` has gone further, for example).

Exits 0 with "skipped" when --root is missing.
"""

from __future__ import annotations

import argparse
import json
import platform
import sys
import time
from pathlib import Path

import kornia
import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))
from bench_nerf import train_preset  # noqa: E402

from nerf_lightning.checkpoints import load_model  # noqa: E402
from nerf_lightning.data.formats import load_blender  # noqa: E402
from nerf_lightning.data.image_stack import as_float_rgb  # noqa: E402
from nerf_lightning.data.scene import evenly_spaced  # noqa: E402
from nerf_lightning.geometry.rays import image_rays  # noqa: E402
from nerf_lightning.plots import plot_psnr_curves  # noqa: E402
from nerf_lightning.rendering import OccupancyGrid, OccupancyGridSampler  # noqa: E402


@torch.no_grad()
def evaluate_fast(ckpt: Path, root: Path, views: int) -> dict:
    """PSNR/SSIM, seconds a frame and samples a ray of a fast checkpoint on ``views`` val views."""
    model, cfg = load_model(ckpt)
    model.eval()
    scene = load_blender(root, downscale=4)
    val = scene.splits["val"]
    val = val.subset(evenly_spaced(len(val), views))
    psnrs, ssims, seconds = [], [], []
    dense, listed, evaluated, rays = 0, 0, 0, 0
    sampler, space = model.sampler, model.space
    # all occupied: plain stepping at the same step
    everything = OccupancyGridSampler(OccupancyGrid(sampler.grid.aabb.tolist(), resolution=1), sampler.step_size, sampler.cone_angle)
    for index in range(len(val)):
        rays_o, rays_d = (x[0] for x in image_rays(val.K[index : index + 1], val.c2w[index : index + 1], val.height, val.width))
        started = time.perf_counter()
        out = model.render_chunked(rays_o, rays_d)
        seconds.append(time.perf_counter() - started)
        rgb = out["rgb"].reshape(val.height, val.width, 3)
        target = as_float_rgb(val.images[index])
        psnrs.append(float(kornia.metrics.psnr(rgb, target, max_val=1.0)))
        ssims.append(float(kornia.metrics.ssim(rgb.permute(2, 0, 1)[None], target.permute(2, 0, 1)[None], window_size=11).mean()))
        for o, d in zip(rays_o.split(model.chunk_size), rays_d.split(model.chunk_size)):
            rays_chunk = space.rays(o, d)
            dense += len(everything.sample(rays_chunk, space, model.field, perturb=False))
            listed += len(sampler.sample(rays_chunk, space, model.field, perturb=False))
            evaluated += int(model.render(o, d)["n_evaluated"])
            rays += len(o)
    return {
        "batch_size": int(cfg["config"]["data"]["batch_size"]), "eval_views": len(val), "psnr": sum(psnrs) / len(psnrs), "ssim": sum(ssims) / len(ssims), "psnr_per_view": psnrs,
        "seconds_per_frame": sum(seconds[1:]) / max(len(seconds) - 1, 1), "frame_size": [val.height, val.width],
        "samples_per_ray": {"plain_stepping": dense / rays, "occupied_cells": listed / rays, "evaluated": evaluated / rays},
        "step_size": sampler.step_size, "grid_occupied_fraction": float(sampler.grid.binary.float().mean()),
    }


def time_to(curve: list[dict], target: float) -> tuple[float | None, int | None]:
    """(training seconds, step) of the first validation at or above ``target``."""
    hit = next((point for point in curve if point["psnr"] >= target), None)
    return (hit["seconds"], hit["step"]) if hit else (None, None)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--root", type=Path, required=True, help="a Blender scene folder (lego)")
    parser.add_argument("--preset", default="fast_blender", help="the fast preset (fast_blender, fast_blender_tensorf)")
    parser.add_argument("--minutes", type=float, default=10.0, help="training wall time of the fast preset")
    parser.add_argument("--steps", type=int, default=None, help="trainer.max_steps (the lr decays over them); default: the preset's")
    parser.add_argument("--val-every", type=int, default=250)
    parser.add_argument("--val-views", type=int, default=1)
    parser.add_argument("--eval-views", type=int, default=20)
    parser.add_argument("--paper-curve", type=Path, default=None, help="bench_nerf.py JSON of the paper MLP without the grid")
    parser.add_argument("--grid-minutes", type=float, default=0.0, help="train the paper MLP with the grid this long (0: skip)")
    parser.add_argument("--grid-target", type=float, default=23.0)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--out", type=Path, required=True)
    parser.add_argument("--run-dir", type=Path, default=None, help="where the runs go (default: outputs/bench/<out's name>)")
    parser.add_argument("--report-only", action="store_true", help="train nothing: redo the comparison, plot and row from --out")
    parser.add_argument("overrides", nargs="*", help="more Hydra overrides for the fast preset, after --")
    args = parser.parse_args()
    if not args.root.exists():
        print(json.dumps({"skipped": f"data not found: {args.root}"}))
        return
    if args.report_only:
        result = json.loads(args.out.read_text())
    else:
        runs = args.run_dir or Path("outputs") / "bench" / args.out.stem
        fast = train_preset(args.preset, runs / "fast", args.root, steps=args.steps, max_minutes=args.minutes, val_every=args.val_every,
                            val_views=args.val_views, seed=args.seed, overrides=args.overrides)
        fast["steps_per_second"] = round(fast["steps"] / fast["training_seconds"], 3)
        fast["eval"] = evaluate_fast(runs / "fast" / "checkpoints" / "last.ckpt", args.root, args.eval_views)
        fast["training_rays_per_second"] = round(fast["eval"]["batch_size"] * fast["steps"] / fast["training_seconds"])
        result = {"fast": fast, "machine": platform.machine(), "threads": torch.get_num_threads(), "torch": torch.__version__}
        if args.grid_minutes > 0:
            result["paper_with_grid"] = train_preset(
                "nerf_blender_grid", runs / "paper_grid", args.root, max_minutes=args.grid_minutes, val_every=args.val_every,
                val_views=args.val_views, target=args.grid_target, seed=args.seed,
            )
    report(result, args)


def report(result: dict, args: argparse.Namespace) -> None:
    """Add the no-grid curve and the time-to-target comparison; write the JSON, the plot and the markdown row."""
    if args.paper_curve is not None and args.paper_curve.exists():
        paper = json.loads(args.paper_curve.read_text())
        result["paper_without_grid"] = {key: paper[key] for key in ("overrides", "steps", "final_val_psnr", "training_seconds", "seconds_per_step", "val_curve")}
    comparison = {}
    for name, key in (("with_grid", "paper_with_grid"), ("without_grid", "paper_without_grid")):
        if key in result:
            seconds, step = time_to(result[key]["val_curve"], args.grid_target)
            comparison[name] = {"seconds": seconds, "step": step, "seconds_per_step": result[key]["seconds_per_step"]}
    if comparison:
        result[f"paper_time_to_{args.grid_target:g}_db"] = comparison
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(result, indent=2) + "\n")

    fast, preset = result["fast"], result["fast"]["preset"]
    curves = {f"{preset} (grid encoding + occupancy grid)": fast["val_curve"]}
    if "paper_with_grid" in result:
        curves["paper MLP + occupancy grid"] = result["paper_with_grid"]["val_curve"]
    if "paper_without_grid" in result:
        curves["paper MLP, no grid"] = result["paper_without_grid"]["val_curve"]
    plot_psnr_curves({name: ([p["seconds"] / 60 for p in curve], [p["psnr"] for p in curve]) for name, curve in curves.items()},
                     args.out.with_suffix(".png"), title=f"{args.root.name} 200x200, 2 CPU cores: validation PSNR", xlabel="training minutes")
    evaluation = fast["eval"]
    row = (f"| {preset} | {args.root.name} 200x200 | {fast['training_seconds'] / 60:.1f} min | {fast['steps']} | {evaluation['psnr']:.2f} dB "
           f"({evaluation['eval_views']} val views) | {evaluation['ssim']:.3f} | {evaluation['samples_per_ray']['plain_stepping']:.0f} / "
           f"{evaluation['samples_per_ray']['occupied_cells']:.1f} / {evaluation['samples_per_ray']['evaluated']:.1f} | "
           f"{fast['training_rays_per_second']} | {evaluation['seconds_per_frame']:.2f} s |")
    args.out.with_suffix(".md").write_text(
        "| preset | scene | training time | steps | held-out PSNR | SSIM | samples a ray: plain / occupied / evaluated | training rays/s | one frame |\n"
        "|---|---|---|---|---|---|---|---|---|\n" + row + "\n")
    print(row)
    print(json.dumps({k: v for k, v in result.items() if k not in ("fast", "paper_with_grid", "paper_without_grid")}, indent=2))


if __name__ == "__main__":
    main()
