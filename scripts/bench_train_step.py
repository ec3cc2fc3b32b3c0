"""Seconds of a training step on this machine's CPU, the hash grids' passes without gradients compiled
(``compile_evaluation``, the default) and as written, alternating in one process.

    .venv/bin/python scripts/bench_train_step.py --ckpt <run>/checkpoints/last.ckpt --out docs/bench/train_step_compiled_cpu.json

A checkpoint's model in training mode, ``scripts/bench_gather.py``'s training step: 1024 random rays of its training
images, the render, the photometric loss against random colours and the sampler's losses, backward, Adam.
``--blocks`` blocks of 10 steps each way (two cycles of a proposal sampler's ``update_every`` of 5: its networks learn
on one step in five and run without gradients on the others), the ways' order alternating, after warm-up steps that
compile. Seed fixed.
"""

from __future__ import annotations

import argparse
import json
import platform
import statistics
import sys
import time
from pathlib import Path

import torch

from nerf_lightning.checkpoints import load_model, load_run_data

sys.path.insert(0, str(Path(__file__).resolve().parent))
from bench_gather import interleaved_seconds, training_step_of  # noqa: E402  the same training step and blocks


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--ckpt", type=Path, required=True, help="a nerf-train checkpoint of a hash-grid field")
    parser.add_argument("--blocks", type=int, default=10)
    parser.add_argument("--out", type=Path, required=True)
    args = parser.parse_args()
    torch.manual_seed(0)
    model, info = load_model(args.ckpt)
    encodings = [module for module in model.modules() if hasattr(module, "compile_evaluation")]
    model.train()
    training_step = training_step_of(model, load_run_data(info["config"]).scene.train)

    def compiled(on: bool) -> None:
        for encoding in encodings:
            encoding.compile_evaluation = on

    started = time.perf_counter()
    for _ in range(10):  # the first passes without gradients compile
        training_step()
    warm_up = time.perf_counter() - started
    seconds = interleaved_seconds(training_step, {"compiled": lambda: compiled(True), "as_written": lambda: compiled(False)},
                                  args.blocks, 10)
    result = {"checkpoint": str(args.ckpt.resolve()), "step": info["global_step"], "torch": torch.__version__,
              "threads": torch.get_num_threads(), "machine": platform.processor() or platform.machine(),
              "warm_up_s": round(warm_up, 2),
              **{way: {"mean_s": round(statistics.mean(values), 4), "median_s": round(statistics.median(values), 4), "steps": len(values)}
                 for way, values in seconds.items()}}
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(result, indent=2) + "\n")
    print(json.dumps(result, indent=2))


if __name__ == "__main__":
    main()
