"""Where a splat training step's time goes: projection, SH, rasterising, the loss (SSIM), the backward pass, Adam and
the strategy, for each rasteriser on the same Gaussians.

    .venv/bin/python scripts/profile_splat_step.py [--preset splat_blender] [--root DIR] [--grow-steps 1500]
        [--steps 20] [--rasterizers pairs tiles] [--out FILE.json] [-- HYDRA OVERRIDES]

Trains ``experiment=<--preset>`` through :func:`nerf_lightning.training.train` (validation, checkpoints, logger off)
for ``--grow-steps`` steps with the fast rasteriser, so that the strategy has grown the Gaussians as a run does, then
times ``--steps`` steps with each of ``--rasterizers`` in turn under ``torch.profiler``. The forward
stages are the CPU time of their labels (``splats.project_and_shade`` where the tiles draw, else ``splats.project``
and ``splats.sh``; ``splats.rasterize``, ``splats.loss``; the strategy's ``splats.strategy``); ``backward`` (the
whole backward pass, the rasteriser's included) and ``adam`` (the optimiser's update) are wall times between
Lightning's hooks; ``step_s`` from the batch's start to its end.
"""

from __future__ import annotations

import argparse
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

import lightning as L
from torch.profiler import ProfilerActivity, profile

import torch

from nerf_lightning.bench.micro import add_common_arguments, compose_preset, finish, seed_everything, start_result
from nerf_lightning.splats.draw import RASTERIZERS
from nerf_lightning.splats.sh import spherical_harmonics
from nerf_lightning.training import train

INSTANCES: list[StageProfiler] = []
STAGES = ("splats.project_and_shade", "splats.project", "splats.sh", "splats.rasterize", "splats.loss",
          "splats.strategy")


class StageProfiler(L.Callback):
    """After ``grow_steps`` steps, profiles ``steps`` steps with each rasteriser of ``rasterizers`` in turn."""

    def __init__(self, grow_steps: int, steps: int, rasterizers: list[str], save_view: str | None = None) -> None:
        self.grow_steps, self.steps, self.rasterizers, self.save_view = grow_steps, steps, rasterizers, save_view
        self._choosers: dict[str, Any] = {}
        self.results: dict[str, Any] = {}
        self._profile: Any = None
        self._mark: dict[str, float] = {}
        self._marks: list[dict[str, float]] = []
        INSTANCES.append(self)  # built by Hydra from the config, read back by main

    def _phase(self, step: int) -> tuple[str, int] | None:
        """(rasteriser, index within its steps) of a step, or None outside the profiled steps (one warm-up step each)."""
        if step < self.grow_steps:
            return None
        index, within = divmod(step - self.grow_steps, self.steps + 1)
        return (self.rasterizers[index], within) if index < len(self.rasterizers) else None

    def on_train_batch_start(self, trainer, pl_module, batch, batch_idx) -> None:
        phase = self._phase(trainer.global_step)
        if phase is None:
            return
        if phase[0] not in self._choosers:  # one a rasteriser, tried (its probe) in its warm-up step
            now = pl_module.rasterizer
            self._choosers[phase[0]] = RASTERIZERS[phase[0]](now.max_pairs, now.antialiased)
        pl_module.rasterizer = self._choosers[phase[0]]
        self._c2w, self._size = batch["c2w"].float(), tuple(batch["image"].shape[:2])
        if phase[1] == 1:
            self._profile = profile(activities=[ProfilerActivity.CPU])
            self._profile.__enter__()
            self._marks = []
        self._mark = {"start": time.perf_counter()}

    def on_before_backward(self, trainer, pl_module, loss) -> None:
        self._mark["forward"] = time.perf_counter()
        if self.save_view and trainer.global_step == self.grow_steps:  # the first profiled view, for bench_rasterize.py
            projection, _, _, _ = pl_module._drawn
            g, ids = pl_module.gaussians, projection.ids
            directions = g.means.detach().index_select(0, ids) - self._c2w[:3, 3]
            colours = spherical_harmonics(g.sh_degree, g.coefficients.detach().index_select(0, ids), directions)
            torch.save({"projection": tuple(value.detach() for value in projection), "colours": colours,
                        "height": self._size[0], "width": self._size[1], "background": pl_module.space.background.cpu(),
                        "gaussians": len(g)}, self.save_view)

    def on_after_backward(self, trainer, pl_module) -> None:
        self._mark["backward"] = time.perf_counter()

    def on_before_optimizer_step(self, trainer, pl_module, optimizer) -> None:
        self._mark["optimizer"] = time.perf_counter()

    def on_train_batch_end(self, trainer, pl_module, outputs, batch, batch_idx) -> None:
        phase = self._phase(trainer.global_step - 1)
        if phase is None or phase[1] == 0:
            return
        self._mark["end"] = time.perf_counter()
        self._marks.append(self._mark)
        if phase[1] == self.steps:
            self._profile.__exit__(None, None, None)
            labels = {event.key: event.cpu_time_total / 1e6 / self.steps for event in self._profile.key_averages()}

            def mean(first: str, last: str) -> float:
                return sum(mark[last] - mark[first] for mark in self._marks) / len(self._marks)

            stages = {name.split(".")[1]: labels.get(name, 0.0) for name in STAGES}
            forward = mean("start", "forward")
            stages["forward_rest"] = forward - sum(stages[key] for key in ("project_and_shade", "project", "sh", "rasterize", "loss"))
            stages["backward"] = mean("forward", "backward")
            stages["adam"] = mean("optimizer", "end")
            ops = sorted(self._profile.key_averages(), key=lambda event: -event.self_cpu_time_total)[:15]
            self.results[phase[0]] = {"step_s": mean("start", "end"), "stages_s": stages, "gaussians": len(pl_module.gaussians),
                                      "top_ops_self_s": {event.key: event.self_cpu_time_total / 1e6 / self.steps for event in ops}}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0], formatter_class=argparse.RawDescriptionHelpFormatter,
                                     epilog="\n".join(__doc__.splitlines()[1:]))
    parser.add_argument("--preset", default="splat_blender")
    parser.add_argument("--root", type=Path, default=None, help="data.root (default: the preset's scene in ../shared/data)")
    parser.add_argument("--grow-steps", type=int, default=1500, help="steps trained before profiling (default 1500)")
    parser.add_argument("--steps", type=int, default=20, help="steps profiled with each rasteriser (default 20)")
    parser.add_argument("--rasterizers", nargs="+", default=["pairs", "tiles"])
    parser.add_argument("--save-view", default=None, help="save the first profiled view's footprints and colours here "
                        "(torch.save; for scripts/bench_rasterize.py)")
    add_common_arguments(parser, warmup=0, repeats=None, device=False)
    parser.add_argument("overrides", nargs="*", help="more Hydra overrides, after --")
    args = parser.parse_args()
    seed_everything(args.seed)
    with tempfile.TemporaryDirectory(prefix="profile_splat_step_") as run_dir:
        total = args.grow_steps + len(args.rasterizers) * (args.steps + 1)
        overrides = [
            f"trainer.max_steps={total}", "data.val_every=null", "data.val_steps=[]", "++trainer.limit_val_batches=0",
            "++trainer.num_sanity_val_steps=0", "trainer.max_time=null", "trainer.enable_progress_bar=false",
            "trainer.enable_model_summary=false", "++trainer.enable_checkpointing=false", "callbacks=none", "~logger",
            "trainer.accelerator=cpu", "trainer.devices=1", f"seed={args.seed}", "model/rasterizer=tiles",
            "+callbacks.stage_profiler._target_=__main__.StageProfiler", f"+callbacks.stage_profiler.grow_steps={args.grow_steps}",
            f"+callbacks.stage_profiler.steps={args.steps}", f"+callbacks.stage_profiler.save_view={args.save_view or 'null'}", f"+callbacks.stage_profiler.rasterizers=[{','.join(args.rasterizers)}]",
            *args.overrides,
        ]
        cfg, root = compose_preset(args.preset, overrides, args.root, output_dir=run_dir)
        train(cfg)
    profiler = INSTANCES[-1]
    result = {**start_result("cpu"), "benchmark": "splat_step_profile", "preset": args.preset,
              "root": None if root is None else str(root), "overrides": args.overrides, "grow_steps": args.grow_steps,
              "steps": args.steps, "rasterizers": profiler.results}
    finish(result, args.out)
    for name, row in profiler.results.items():
        stages = ", ".join(f"{key} {1000 * value:.1f}" for key, value in row["stages_s"].items())
        print(f"{args.preset} {name}: {1000 * row['step_s']:.1f} ms a step with {row['gaussians']} Gaussians ({stages} ms)",
              file=sys.stderr)


if __name__ == "__main__":
    main()
