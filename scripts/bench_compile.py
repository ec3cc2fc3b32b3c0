"""Does torch.compile pay off for the hash-grid field on this machine? Eager against compiled, compile time counted.

    .venv/bin/python scripts/bench_compile.py --out docs/bench/compile_hash_field.json

Times ``--steps`` optimiser steps (forward, backward, Adam) of the ``experiment=fast_blender`` field on batches
of about ``--samples`` random points (the count varies by up to 10% a step, as packed samples do), eagerly and
through ``torch.compile`` (default inductor backend). The compiled run's first steps include the compilation
(and the recompile for dynamic shapes); the JSON has the compile time, the steady seconds a step
of both, and after how many steps the compiled one has paid its compilation back (null if never).
"""

from __future__ import annotations

import argparse
import json
import platform
import time
from pathlib import Path

import torch

from nerf_lightning.fields import GridField, HashGridEncoding


def run(compiled: bool, steps: int, samples: int, seed: int) -> dict:
    torch.manual_seed(seed)
    field = GridField(aabb=[-1.5, -1.5, -1.5, 1.5, 1.5, 1.5], encoding=HashGridEncoding(n_levels=8, max_resolution=1024))
    optimizer = torch.optim.Adam(field.parameters(), lr=1e-2, eps=1e-15)
    generator = torch.Generator().manual_seed(seed)

    def loss_of(points: torch.Tensor, directions: torch.Tensor, target: torch.Tensor) -> torch.Tensor:
        out = field(points, directions)
        return ((out["rgb"] - target) ** 2).mean() + 1e-3 * out["density"].mean()

    step_fn = torch.compile(loss_of) if compiled else loss_of
    seconds = []
    for _ in range(steps):
        count = samples + int(torch.randint(-samples // 10, samples // 10, (), generator=generator))  # packed: varies a step
        points = torch.rand(count, 3, generator=generator) * 3 - 1.5
        directions = torch.nn.functional.normalize(torch.randn(count, 3, generator=generator), dim=-1)
        target = torch.rand(count, 3, generator=generator)
        started = time.perf_counter()
        optimizer.zero_grad()
        step_fn(points, directions, target).backward()
        optimizer.step()
        seconds.append(time.perf_counter() - started)
    steady = sorted(seconds[5:])[len(seconds[5:]) // 2]  # the median after the first five
    return {"first_five_steps_seconds": round(sum(seconds[:5]), 3), "steady_seconds_per_step": round(steady, 4)}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--steps", type=int, default=30)
    parser.add_argument("--samples", type=int, default=20_000, help="points a step (about 2048 rays x 10 samples)")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--out", type=Path, required=True)
    args = parser.parse_args()
    eager = run(False, args.steps, args.samples, args.seed)
    try:
        compiled = run(True, args.steps, args.samples, args.seed)
    except Exception as error:  # no compiler, unsupported op: that is the answer too
        compiled = {"error": f"{type(error).__name__}: {error}"[:500]}
    result = {"samples": args.samples, "steps": args.steps, "eager": eager, "compiled": compiled,
              "torch": torch.__version__, "threads": torch.get_num_threads(), "machine": platform.machine()}
    if "steady_seconds_per_step" in compiled:
        compile_seconds = compiled["first_five_steps_seconds"] - 5 * compiled["steady_seconds_per_step"]
        saving = eager["steady_seconds_per_step"] - compiled["steady_seconds_per_step"]
        result["compile_seconds"] = round(compile_seconds, 2)
        result["speedup"] = round(eager["steady_seconds_per_step"] / compiled["steady_seconds_per_step"], 3)
        result["steps_to_pay_back"] = round(compile_seconds / saving) if saving > 0 else None
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(result, indent=2) + "\n")
    print(json.dumps(result, indent=2))


if __name__ == "__main__":
    main()
