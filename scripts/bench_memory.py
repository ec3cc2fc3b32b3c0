"""Peak memory of training on a full-size scene: nerf-train in a child process, its peak resident memory, JSON out.

    .venv/bin/python scripts/bench_memory.py --root ../shared/data/nerf_synthetic/lego --out docs/bench/memory_lego800.json

Trains ``experiment=<--preset>`` (default ``fast_blender``) at ``data.scene.downscale=1`` (lego: 100 train and 100 val
images of 800x800) for ``--steps`` steps with one validation view, in a child process, and reads the child's peak
resident set size (``getrusage``). Also reports the bytes of the loaded images themselves, and what precomputed
rays of every training pixel (origin and direction, float32) would have added. Exits 0 with "skipped" when --root is
missing.
"""

from __future__ import annotations

import argparse
import json
import platform
import resource
import subprocess
import sys
import tempfile
import time
from pathlib import Path

GIB = 1024**3


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--root", type=Path, required=True)
    parser.add_argument("--preset", default="fast_blender")
    parser.add_argument("--steps", type=int, default=20)
    parser.add_argument("--out", type=Path, required=True)
    parser.add_argument("overrides", nargs="*", help="more Hydra overrides, after --")
    args = parser.parse_args()
    if not args.root.exists():
        print(json.dumps({"skipped": f"data not found: {args.root}"}))
        return

    with tempfile.TemporaryDirectory() as run:
        command = [sys.executable, "-m", "nerf_lightning.train", f"experiment={args.preset}", f"data.root={args.root.resolve()}",
                   "data.scene.downscale=1", f"trainer.max_steps={args.steps}", f"data.val_every={args.steps}", "data.val_views=1",
                   "trainer.enable_progress_bar=false", f"hydra.run.dir={run}", *args.overrides]
        started = time.perf_counter()
        subprocess.run(command, check=True, capture_output=True, text=True)
        seconds = time.perf_counter() - started
        peak = resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss * 1024  # kilobytes on Linux
        metrics = json.loads((Path(run) / "metrics.json").read_text())

    from nerf_lightning.data.formats import load_blender

    scene = load_blender(args.root, downscale=1)
    image_bytes = {name: views.images.nbytes for name, views in scene.splits.items() if views.images is not None}
    train = scene.train
    pixels = len(train) * train.height * train.width
    result = {
        "preset": args.preset, "root": str(args.root), "steps": metrics["step"], "seconds": round(seconds, 1),
        "peak_rss_gib": round(peak / GIB, 3), "train_views": len(train), "size": [train.height, train.width],
        "image_gib_by_split": {name: round(size / GIB, 3) for name, size in image_bytes.items()},
        "image_gib_held": round(sum({id(scene.splits[name].images): size for name, size in image_bytes.items()}.values()) / GIB, 3),
        "precomputed_rays_would_add_gib": round(pixels * 6 * 4 / GIB, 3),
        "torch": __import__("torch").__version__, "machine": platform.machine(),
    }
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(result, indent=2) + "\n")
    print(json.dumps(result, indent=2))


if __name__ == "__main__":
    main()
