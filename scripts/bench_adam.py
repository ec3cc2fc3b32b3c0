"""Adam's step over a preset's parameters, three ways: a loop over the parameters (torch's default on a CPU), foreach and
fused. Medians of ``--repeats`` steps after a warm-up, the gradients random and fixed; JSON out.

    .venv/bin/python scripts/bench_adam.py --preset nerfacto_forward_cpu --out docs/bench/adam_step_cpu.json

The model is built from the preset's config as ``nerf-train`` builds it (no data is read: the per-view tables stay
empty), so the hash tables and MLPs are the preset's sizes.
"""

from __future__ import annotations

import argparse
import json
import platform
import statistics
import time
from pathlib import Path

import torch
from hydra.utils import instantiate

from nerf_lightning.config import compose_config

WAYS = {"loop": {"foreach": False}, "foreach": {"foreach": True}, "fused": {"fused": True}}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--preset", default="nerfacto_forward_cpu")
    parser.add_argument("--repeats", type=int, default=20)
    parser.add_argument("--out", type=Path, required=True)
    args = parser.parse_args()
    torch.manual_seed(0)
    cfg = compose_config([f"experiment={args.preset}", "paths.output_dir=/tmp/bench_adam"])
    model = instantiate(cfg.model)
    params = [p for p in model.parameters() if p.requires_grad]
    for p in params:
        p.grad = torch.randn_like(p)
    result = {"preset": args.preset, "parameters": sum(p.numel() for p in params), "tensors": len(params),
              "torch": torch.__version__, "threads": torch.get_num_threads(), "machine": platform.processor() or platform.machine(),
              "seconds_median": {}}
    for name, options in WAYS.items():
        optimizer = torch.optim.Adam(params, lr=1e-2, eps=1e-15, **options)
        optimizer.step()  # warm-up: the state is made
        seconds = []
        for _ in range(args.repeats):
            started = time.perf_counter()
            optimizer.step()
            seconds.append(time.perf_counter() - started)
        result["seconds_median"][name] = round(statistics.median(seconds), 5)
        print(name, f"{1000 * result['seconds_median'][name]:.1f} ms", flush=True)
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(result, indent=2) + "\n")


if __name__ == "__main__":
    main()
