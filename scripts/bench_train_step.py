"""Seconds of a training step of a preset, trained through the library's own step (nerf_lightning.training.train).

    .venv/bin/python scripts/bench_train_step.py [--preset fast_blender] [--root DIR] [--steps 100] [--warmup 10]
        [--device auto] [--seed 0] [--out FILE.json] [-- HYDRA OVERRIDES]
    .venv/bin/python scripts/bench_train_step.py --preset fast --steps 20 -- data.scene.size=16   # no data needed

Composes ``experiment=<--preset>`` as ``nerf-train`` does (its ``data.root``: ``--root``, else the preset's scene in
../shared/data, lego for fast_blender; extra Hydra overrides after ``--``) and trains it with
:func:`nerf_lightning.training.train` for ``--warmup`` + ``--steps`` steps, validation, checkpoints, snapshots, logger
and progress bar off, a :class:`~nerf_lightning.bench.micro.StepTimer` timing the ``--steps`` steps after the warm-up
(waiting for a GPU at each mark): ``step`` is the training step itself (forward, losses, backward, optimiser step),
``loop`` the whole loop from one step's end to the next's (drawing the batch included). Both include the periodic
work of the steps they time (an occupancy grid's refresh every ``update_every`` steps, a proposal network's
update): the mean counts it, the median mostly not. Rays a second: ``data.batch_size`` over the median. Prints the
JSON (and writes it with ``--out``); exits 0 with ``{"skipped": ...}`` when the scene is missing.
"""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
from pathlib import Path

from nerf_lightning.bench.micro import add_common_arguments, compose_preset, finish, parse_device, seed_everything, start_result, summarize
from nerf_lightning.training import train


def accelerator_overrides(device: str) -> list[str]:
    """``trainer.accelerator`` (and ``trainer.devices``) for ``--device``: auto leaves the preset's choice."""
    device = device.strip().lower()
    if device == "auto":
        return []
    if device == "cpu":
        return ["trainer.accelerator=cpu", "trainer.devices=1"]
    if device == "mps":
        return ["trainer.accelerator=mps", "trainer.devices=1"]
    index = device.partition(":")[2] or "0"  # cuda or cuda:N
    return ["trainer.accelerator=gpu", f"trainer.devices=[{index}]"]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0], formatter_class=argparse.RawDescriptionHelpFormatter,
                                     epilog="\n".join(__doc__.splitlines()[1:]))
    parser.add_argument("--preset", default="fast_blender", help="an experiment preset (default fast_blender)")
    parser.add_argument("--root", type=Path, default=None, help="data.root (default: the preset's scene in ../shared/data)")
    parser.add_argument("--steps", type=int, default=100, help="steps timed after the warm-up (default 100)")
    parser.add_argument("--count-operators", action="store_true",
                        help="count the PyTorch operators each timed step dispatches (nerf_lightning.bench.operators), not "
                             "its time: the counting slows the steps, so the times of such a run are not reported")
    add_common_arguments(parser, warmup=10, repeats=None)
    parser.add_argument("overrides", nargs="*", help="more Hydra overrides, after --")
    args = parser.parse_args()
    if args.steps < 2 or args.warmup < 0:
        raise SystemExit("--steps must be >= 2 and --warmup >= 0")
    parse_device(args.device)  # one line for a device this machine lacks
    seed_everything(args.seed)

    with tempfile.TemporaryDirectory(prefix="bench_train_step_") as run_dir:
        timings, operators = Path(run_dir) / "step_seconds.json", Path(run_dir) / "operators.json"
        counter = [] if not args.count_operators else [
            "+callbacks.operators._target_=nerf_lightning.bench.operators.StepOperatorCounter",
            f"+callbacks.operators.first={args.warmup + 1}", f"+callbacks.operators.last={args.warmup + args.steps}",
            f"+callbacks.operators.path='{operators}'"]
        overrides = [
            f"trainer.max_steps={args.warmup + args.steps}", "data.val_every=null", "data.val_steps=[]",
            "++trainer.limit_val_batches=0", "++trainer.num_sanity_val_steps=0", "trainer.max_time=null",
            "trainer.enable_progress_bar=false", "trainer.enable_model_summary=false", "++trainer.enable_checkpointing=false",
            "callbacks=none", "~logger",
            f"seed={args.seed}", *accelerator_overrides(args.device),
            "+callbacks.step_timer._target_=nerf_lightning.bench.micro.StepTimer",
            f"+callbacks.step_timer.warmup_steps={args.warmup}", f"+callbacks.step_timer.path='{timings}'",
            *counter, *args.overrides,
        ]
        cfg, root = compose_preset(args.preset, overrides, args.root, output_dir=run_dir)
        metrics = train(cfg)
        timed = json.loads(timings.read_text())
        counted = json.loads(operators.read_text()) if args.count_operators else None

    step, loop = summarize(timed["step_s"]), summarize(timed["loop_s"])
    batch_size = cfg.data.get("batch_size")  # rays a step; a model of Gaussians draws whole views (data=views), which have none
    result = {
        **start_result(timed["device"] or args.device),
        "benchmark": "train_step", "preset": args.preset, "root": None if root is None else str(root), "overrides": args.overrides,
        "device": timed["device"], "precision": str(cfg.trainer.precision), "callbacks": list(cfg.get("callbacks") or {}), "seed": args.seed, "batch_size": batch_size,
        "warmup_steps": args.warmup, "steps": len(timed["step_s"]), "global_step": metrics["step"],
        "rays_per_second": batch_size / step["median_s"] if batch_size else None,
        "rays_per_second_loop": batch_size / loop["median_s"] if batch_size else None,
        "samples_per_ray": metrics.get("train/samples_per_ray"), "final_train_loss": metrics.get("train/loss"),
        "step": step, "loop": loop,
    }
    if counted is not None:
        result.update(step=None, loop=None, rays_per_second=None, rays_per_second_loop=None, operators=counted)
        finish(result, args.out)
        top = ", ".join(f"{count:g} {name}" for name, count in list(counted["per_step"].items())[:8])
        print(f"{args.preset}: {counted['total']:g} operators a step over {counted['steps']} steps ({top}, ...)", file=sys.stderr)
        return
    finish(result, args.out)
    rays = f", {result['rays_per_second']:,.0f} rays/s" if batch_size else ""
    print(f"{args.preset}: {1000 * step['median_s']:.1f} ms a step (median; mean {1000 * step['mean_s']:.1f} ms, "
          f"loop {1000 * loop['median_s']:.1f} ms){rays} on {timed['device']}", file=sys.stderr)


if __name__ == "__main__":
    main()
