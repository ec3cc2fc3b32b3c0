"""Seconds of a training step on this machine's CPU, the hash grids' passes without gradients compiled
(``compile_evaluation``, the default) and as written, alternating in one process.

    .venv/bin/python scripts/bench_train_step.py --ckpt <run>/checkpoints/last.ckpt --out docs/bench/train_step_compiled_cpu.json

A checkpoint's model in training mode from its last step on: 1024 random rays of its training images a step, the
render, the photometric loss against random colours and the sampler's losses, backward, fused Adam at a small
learning rate. ``--blocks`` blocks of 10 steps each way (two cycles of a proposal sampler's ``update_every`` of 5: its
networks learn on one step in five and run without gradients on the others), the ways' order alternating, after
warm-up steps that compile. Seed fixed.
"""

from __future__ import annotations

import argparse
import json
import platform
import statistics
import time
from pathlib import Path

import torch
import torch.nn.functional as F

from nerf_lightning.checkpoints import load_model, load_run_data
from nerf_lightning.geometry.rays import image_rays


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--ckpt", type=Path, required=True, help="a nerf-train checkpoint of a hash-grid field")
    parser.add_argument("--blocks", type=int, default=10)
    parser.add_argument("--out", type=Path, required=True)
    args = parser.parse_args()
    torch.manual_seed(0)
    model, info = load_model(args.ckpt, kind="radiance_field", command="bench_train_step")
    encodings = [module for module in model.modules() if hasattr(module, "compile_evaluation")]
    train = load_run_data(info["config"]).scene.train
    origins, directions = image_rays(train.K, train.c2w, train.height, train.width)
    origins, directions = origins.reshape(-1, 3), directions.reshape(-1, 3)
    optimizer = torch.optim.Adam(model.parameters(), lr=1e-5, eps=1e-15, fused=True)
    model.train()
    step_index = [int(info["global_step"])]

    def step() -> float:
        started = time.perf_counter()
        rays = torch.randint(0, len(origins), (1024,))
        step_index[0] += 1
        model.sampler.update(step_index[0], model.field)
        out = model.render(origins[rays], directions[rays], perturb=True)
        target = torch.rand(1024, 3)
        loss = F.mse_loss(out["rgb"], target) + sum(model.sampler.losses(out["samples"], out, target).values())
        optimizer.zero_grad()
        loss.backward()
        optimizer.step()
        return time.perf_counter() - started

    def set_compiled(compiled: bool) -> None:
        for encoding in encodings:
            encoding.compile_evaluation = compiled

    set_compiled(True)
    warm_up = [step() for _ in range(10)]
    seconds = {"compiled": [], "as_written": []}
    for block in range(args.blocks):
        ways = list(seconds) if block % 2 == 0 else list(seconds)[::-1]
        for way in ways:
            set_compiled(way == "compiled")
            seconds[way] += [step() for _ in range(10)]
    result = {"checkpoint": str(args.ckpt.resolve()), "step": info["global_step"], "torch": torch.__version__,
              "threads": torch.get_num_threads(), "machine": platform.processor() or platform.machine(),
              "warm_up_s": round(sum(warm_up), 2),
              **{way: {"mean_s": round(statistics.mean(values), 4), "median_s": round(statistics.median(values), 4), "steps": len(values)}
                 for way, values in seconds.items()}}
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(result, indent=2) + "\n")
    print(json.dumps(result, indent=2))


if __name__ == "__main__":
    main()
