"""A radiance-field preset trained for real: validation PSNR against steps and training time, JSON out.

    .venv/bin/python scripts/bench_nerf.py --preset nerf_blender --root ../shared/data/nerf_synthetic/lego \\
        --max-minutes 60 --val-every 100 --target 23 --out docs/bench/nerf_lego.json

Trains ``experiment=<preset>`` through the shipped configs (extra Hydra overrides after ``--``) until
``--steps`` or ``--max-minutes`` of wall time, or until the validation PSNR reaches ``--target`` (then it
stops). Writes the JSON (curve of val/psnr with steps and training seconds, seconds per step, time to the
target or null) and a plot beside it, and keeps the run folder (checkpoints: resume with --resume).
Exits 0 with "skipped" when --root is given and missing.
"""

from __future__ import annotations

import argparse
import json
import platform
import time
from pathlib import Path

import torch

from nerf_lightning.config import compose_config
from nerf_lightning.plots import plot_psnr_curves
from nerf_lightning.training import train


def train_preset(
    preset: str,
    run_dir: Path,
    root: Path | None = None,
    steps: int | None = 200_000,
    max_minutes: float = 60.0,
    val_every: int = 100,
    val_views: int = 2,
    target: float | None = None,
    seed: int = 0,
    resume: bool = False,
    overrides: list[str] | tuple[str, ...] = (),
) -> dict:
    """Train ``experiment=<preset>`` into ``run_dir`` (see the module's docstring); returns the result dict.

    ``steps`` None keeps the preset's ``trainer.max_steps`` (and so its learning-rate schedule)."""
    seconds_budget = round(max_minutes * 60)
    max_time = f"{seconds_budget // 86400:02d}:{seconds_budget // 3600 % 24:02d}:{seconds_budget // 60 % 60:02d}:{seconds_budget % 60:02d}"
    all_overrides = [
        f"experiment={preset}", *([f"trainer.max_steps={steps}"] if steps else []), f"data.val_every={val_every}",
        f"data.val_views={val_views}", f"seed={seed}", f"paths.output_dir={run_dir}",
        "trainer.enable_progress_bar=false", f"trainer.max_time='{max_time}'",
        *overrides,
    ]
    if root is not None:
        all_overrides.append(f"data.root={root.resolve()}")
    if target is not None:
        all_overrides.append(f"+callbacks.stop_at_target={{_target_: lightning.pytorch.callbacks.EarlyStopping, monitor: val/psnr, "
                             f"mode: max, stopping_threshold: {target}, patience: 1000000, check_on_train_epoch_end: false}}")
    if resume:
        all_overrides.append(f"ckpt_path={run_dir / 'checkpoints' / 'last.ckpt'}")
    cfg = compose_config(all_overrides)
    started = time.perf_counter()
    metrics = train(cfg)
    wall = time.perf_counter() - started

    history = json.loads((run_dir / "psnr_history.json").read_text())
    step_list, seconds = history["train_step"], history["train_seconds"]
    reached = next((t for t, p in zip(history["val_seconds"], history["val_psnr"]) if target and p >= target), None)
    reached_step = next((s for s, p in zip(history["val_step"], history["val_psnr"]) if target and p >= target), None)
    return {
        "preset": preset, "root": str(root) if root else None, "overrides": all_overrides, "seed": seed,
        "steps": metrics["step"], "final_val_psnr": metrics.get("val/psnr"), "final_val_ssim": metrics.get("val/ssim"),
        "final_val_depth_error": metrics.get("val/depth_error"), "final_train_samples_per_ray": metrics.get("train/samples_per_ray"),
        "training_seconds": seconds[-1] if seconds else None, "wall_seconds_with_validation": round(wall, 1),
        "seconds_per_step": round((seconds[-1] - seconds[0]) / max(step_list[-1] - step_list[0], 1), 4) if len(step_list) > 1 else None,
        "target_psnr": target, "target_reached_at_seconds": reached, "target_reached_at_step": reached_step,
        "val_curve": [{"step": s, "seconds": t, "psnr": round(p, 3)} for s, t, p in zip(history["val_step"], history["val_seconds"], history["val_psnr"])],
        "torch": torch.__version__, "threads": torch.get_num_threads(), "machine": platform.machine(),
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--preset", default="nerf_procedural")
    parser.add_argument("--root", type=Path, default=None, help="data.root of the preset (a Blender folder or an npz)")
    parser.add_argument("--steps", type=int, default=200_000)
    parser.add_argument("--max-minutes", type=float, default=60.0)
    parser.add_argument("--val-every", type=int, default=100)
    parser.add_argument("--val-views", type=int, default=2)
    parser.add_argument("--target", type=float, default=None, help="stop once val/psnr reaches this (dB)")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--run-dir", type=Path, default=None, help="where the run goes (default: beside --out)")
    parser.add_argument("--resume", action="store_true", help="continue from <run-dir>/checkpoints/last.ckpt")
    parser.add_argument("--out", type=Path, required=True)
    parser.add_argument("overrides", nargs="*", help="more Hydra overrides, after --")
    args = parser.parse_args()

    if args.root is not None and not args.root.exists():
        print(json.dumps({"skipped": f"data not found: {args.root}"}))
        return
    result = train_preset(
        args.preset, args.run_dir or args.out.with_suffix(""), args.root, args.steps, args.max_minutes, args.val_every,
        args.val_views, args.target, args.seed, args.resume, args.overrides,
    )
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(result, indent=2) + "\n")
    curve = result["val_curve"]
    plot_psnr_curves({f"{args.preset} val": ([c["seconds"] for c in curve], [c["psnr"] for c in curve])}, args.out.with_suffix(".png"),
                     title=f"{args.preset}: validation PSNR against training time", xlabel="training seconds")
    print(json.dumps({k: v for k, v in result.items() if k not in ("val_curve", "overrides")}, indent=2))


if __name__ == "__main__":
    main()
