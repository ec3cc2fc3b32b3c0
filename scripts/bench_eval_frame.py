"""Seconds of one evaluation frame on this machine's CPU, hash-grid encodings compiled (the default) and in plain
PyTorch, with where the time goes and what the first compiled frame pays for compiling.

    .venv/bin/python scripts/bench_eval_frame.py --ckpt <run>/checkpoints/last.ckpt --out docs/bench/fern_frame_cpu.json

Renders the run's first held-out view at the run's resolution as ``nerf-eval`` does (``render_view``): once compiled
first (compilation included; run it with ``TORCHINDUCTOR_CACHE_DIR`` set to an empty folder for a machine's first
time, whose compilation is not yet cached on disk), then ``--repeats`` times each way, alternating. Each frame's
seconds are split into the sampler's, the field's encoding's, the rest of the field's and the rest of the renderer's.
"""

from __future__ import annotations

import argparse
import json
import platform
import statistics
import time
from collections import defaultdict
from pathlib import Path

import torch

from nerf_lightning.checkpoints import load_model
from nerf_lightning.outputs.evaluation import views_to_evaluate



def timed(seconds: dict[str, float], obj: object, name: str, part: str) -> None:
    """Replace ``obj.name`` (a method) by itself adding the seconds of each call to ``seconds[part]``."""
    function = getattr(obj, name)

    def wrapper(*args, **kwargs):
        started = time.perf_counter()
        result = function(*args, **kwargs)
        seconds[part] += time.perf_counter() - started
        return result

    setattr(obj, name, wrapper)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--ckpt", type=Path, required=True, help="a nerf-train checkpoint of a hash-grid field")
    parser.add_argument("--repeats", type=int, default=2, help="frames timed each way after the first")
    parser.add_argument("--out", type=Path, required=True)
    args = parser.parse_args()
    model, info = load_model(args.ckpt)
    views = views_to_evaluate(model, info["config"])
    encodings = [module for module in model.modules() if hasattr(module, "compile_evaluation")]
    if not encodings:
        raise SystemExit(f"{args.ckpt}: no hash-grid encoding in this model, nothing compiled to compare")
    seconds: dict[str, float] = defaultdict(float)
    timed(seconds, model.sampler, "sample", "sampler")
    timed(seconds, model.field, "forward", "field")
    timed(seconds, model.field.encoding, "forward", "field_encoding")

    def frame(compiled: bool) -> tuple[float, dict[str, float], torch.Tensor]:
        for encoding in encodings:
            encoding.compile_evaluation = compiled
        seconds.clear()
        started = time.perf_counter()
        rgb = model.render_view(views.K[0], views.c2w[0], views.height, views.width)["rgb"]
        total = time.perf_counter() - started
        parts = {"sampler": seconds["sampler"], "field_encoding": seconds["field_encoding"],
                 "field_rest": seconds["field"] - seconds["field_encoding"],
                 "renderer_rest": total - seconds["sampler"] - seconds["field"]}
        return total, parts, rgb

    first, _, compiled_rgb = frame(True)
    print(f"first compiled frame: {first:.2f} s", flush=True)
    runs = {"compiled": [], "plain": []}
    for _ in range(args.repeats):
        for way in ("plain", "compiled"):
            total, parts, rgb = frame(way == "compiled")
            runs[way].append((total, parts))
            print(f"{way}: {total:.2f} s", {key: round(value, 2) for key, value in parts.items()}, flush=True)
            if way == "plain":
                plain_rgb = rgb
    result = {
        "checkpoint": str(args.ckpt.resolve()), "step": info["global_step"], "view": views.names[0],
        "height": views.height, "width": views.width, "torch": torch.__version__, "threads": torch.get_num_threads(),
        "machine": platform.processor() or platform.machine(), "first_compiled_frame_s": round(first, 2),
        "max_abs_rgb_difference": float((compiled_rgb - plain_rgb).abs().max()),
    }
    for way, frames in runs.items():
        result[way] = {"frames_s": [round(total, 2) for total, _ in frames],
                       "median_s": round(statistics.median(total for total, _ in frames), 2),
                       "parts_s": {key: round(statistics.median(parts[key] for _, parts in frames), 2) for key in frames[0][1]}}
    result["first_frame_compile_s"] = round(first - result["compiled"]["median_s"], 2)
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(result, indent=2) + "\n")
    print(json.dumps(result, indent=2))


if __name__ == "__main__":
    main()
