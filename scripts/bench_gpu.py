"""The fast preset on one GPU: held-out PSNR against training minutes, steps and rays a second, frame time, peak
memory, float32 against bf16-mixed; JSON with the device, torch and CUDA versions, and a plot.

    python scripts/bench_gpu.py --root ../shared/data/nerf_synthetic/lego --minutes 1 2 5 10 \\
        --precisions 32 bf16-mixed --out docs/bench/gpu_lego.json

For each precision: trains ``experiment=<--preset>`` (default ``fast_blender_gpu``: lego at 800x800) for the
largest of ``--minutes`` of training time with a checkpoint as training time reaches each mark
(:class:`~nerf_lightning.callbacks.CheckpointAtMinutes`; validating costs the clock nothing), then scores each
checkpoint on ``--eval-views`` evenly spaced views of the val split (100: all of them) with
:func:`~nerf_lightning.outputs.evaluation.evaluate_views`, the same metrics as ``nerf-eval``, timing each frame.
``--device cpu`` runs it on a CPU (tiny settings, to check the script). Exits 0 with "skipped" when --root is missing.
"""

from __future__ import annotations

import argparse
import json
import platform
import sys
import time
from pathlib import Path

import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))
from bench_nerf import train_preset  # noqa: E402

from nerf_lightning.checkpoints import load_model, read_checkpoint  # noqa: E402
from nerf_lightning.data.formats import load_blender  # noqa: E402
from nerf_lightning.data.scene import evenly_spaced  # noqa: E402
from nerf_lightning.devices import resolve_device, synchronize  # noqa: E402
from nerf_lightning.outputs.evaluation import evaluate_views  # noqa: E402
from nerf_lightning.plots import plot_psnr_curves  # noqa: E402


def device_info(device: torch.device) -> dict:
    info = {"device": str(device), "torch": torch.__version__, "cuda": torch.version.cuda, "machine": platform.machine(),
            "cpu_threads": torch.get_num_threads()}
    if device.type == "cuda":
        props = torch.cuda.get_device_properties(device)
        info.update(name=props.name, memory_gib=round(props.total_memory / 2**30, 1), multiprocessors=props.multi_processor_count)
    return info


@torch.no_grad()
def evaluate_checkpoint(ckpt: Path, views, device: torch.device) -> dict:
    """PSNR/SSIM over ``views`` and milliseconds a frame (the first, warming up, left out of the mean)."""
    model, _ = load_model(ckpt, device=str(device))
    model.eval()
    seconds = []
    rows = []
    for index in range(len(views)):
        one = views.subset([index])
        synchronize(device)
        started = time.perf_counter()
        rows += evaluate_views(model, one)
        synchronize(device)
        seconds.append(time.perf_counter() - started)
    timed = seconds[1:] or seconds
    return {
        "psnr": sum(r["psnr"] for r in rows) / len(rows), "ssim": sum(r["ssim"] for r in rows) / len(rows), "views": len(rows),
        "ms_per_frame": round(1000 * sum(timed) / len(timed), 1), "psnr_per_view": [round(r["psnr"], 3) for r in rows],
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--root", type=Path, required=True, help="a Blender scene folder (lego)")
    parser.add_argument("--preset", default="fast_blender_gpu")
    parser.add_argument("--minutes", type=float, nargs="+", default=[1, 2, 5, 10], help="training minutes to score")
    parser.add_argument("--precisions", nargs="+", default=["32", "bf16-mixed"], help="trainer.precision values")
    parser.add_argument("--steps", type=int, default=None, help="trainer.max_steps (the lr decays over them); default: the preset's")
    parser.add_argument("--eval-views", type=int, default=100)
    parser.add_argument("--device", default="cuda", help="cuda | cpu (cpu: to check the script on tiny settings)")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--out", type=Path, required=True)
    parser.add_argument("--run-dir", type=Path, default=None, help="where the runs go (default: outputs/bench/<out's name>)")
    parser.add_argument("overrides", nargs="*", help="more Hydra overrides for the preset, after --")
    args = parser.parse_args()
    if not args.root.exists():
        print(json.dumps({"skipped": f"data not found: {args.root}"}))
        return
    device = resolve_device(args.device)
    runs = args.run_dir or Path("outputs") / "bench" / args.out.stem
    result = {"device": device_info(device), "preset": args.preset, "seed": args.seed, "runs": {}}
    views = None
    for precision in args.precisions:
        run_dir = runs / precision
        if device.type == "cuda":
            torch.cuda.empty_cache()
            torch.cuda.reset_peak_memory_stats(device)
        minutes = ", ".join(f"{m:g}" for m in args.minutes)
        run = train_preset(
            args.preset, run_dir, args.root, steps=args.steps, max_minutes=max(args.minutes), val_every=10**9, val_views=1, seed=args.seed,
            overrides=[f"trainer.precision={precision}", f"trainer.accelerator={'gpu' if device.type == 'cuda' else 'cpu'}",
                       f"+callbacks.minute_marks={{_target_: nerf_lightning.callbacks.CheckpointAtMinutes, dirpath: {run_dir / 'marks'}, minutes: [{minutes}]}}",
                       *args.overrides],
        )
        run["peak_gpu_memory_gib"] = round(torch.cuda.max_memory_allocated(device) / 2**30, 2) if device.type == "cuda" else None
        run.pop("val_curve", None)
        marks = json.loads((run_dir / "marks" / "marks.json").read_text())
        config = read_checkpoint(marks[0]["path"])["nerf_lightning"]["config"]
        if views is None:
            val = load_blender(args.root, downscale=int(config["data"]["scene"]["downscale"])).splits["val"]
            views = val.subset(evenly_spaced(len(val), args.eval_views))
        curve = []
        for mark in marks:
            scores = evaluate_checkpoint(Path(mark["path"]), views, device)
            curve.append({**{k: mark[k] for k in ("minutes", "step", "training_seconds")}, **scores})
            print(f"{precision}: {mark['minutes']:g} min (step {mark['step']}): {scores['psnr']:.2f} dB, SSIM {scores['ssim']:.4f}, "
                  f"{scores['ms_per_frame']:.0f} ms a frame", flush=True)
        run["curve"] = curve
        run["training_seconds"] = marks[-1]["training_seconds"]  # the clock of the last weights (the history's is per log step)
        seconds = run["training_seconds"]
        run["steps_per_second"] = round(marks[-1]["step"] / seconds, 2)
        run["batch_size"] = int(config["data"]["batch_size"])
        run["rays_per_second"] = round(marks[-1]["step"] * run["batch_size"] / seconds)
        result["runs"][precision] = run
        args.out.parent.mkdir(parents=True, exist_ok=True)
        args.out.write_text(json.dumps(result, indent=2) + "\n")
    plot_psnr_curves({f"{args.preset}, precision {p}": ([c["training_seconds"] / 60 for c in r["curve"]], [c["psnr"] for c in r["curve"]])
                      for p, r in result["runs"].items()},
                     args.out.with_suffix(".png"), title=f"{args.root.name}, {result['device'].get('name', device.type)}: held-out PSNR ({len(views)} val views)",
                     xlabel="training minutes")
    for precision, run in result["runs"].items():
        points = ", ".join(f"{c['minutes']:g} min {c['psnr']:.2f} dB" for c in run["curve"])
        print(f"| {precision} | {points} | {run['steps_per_second']} steps/s | {run['rays_per_second']:.0f} rays/s | "
              f"{run['curve'][-1]['ms_per_frame']:.0f} ms a frame | {run['peak_gpu_memory_gib']} GiB |")


if __name__ == "__main__":
    main()
