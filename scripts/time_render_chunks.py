"""Seconds to render held-out view 0 of a checkpoint's scene at several ``model.chunk_size`` values, each twice;
``--scale`` renders it smaller (K scaled alike) and also gives the time a full-size frame would take at that rate.

    .venv/bin/python scripts/time_render_chunks.py <run>/checkpoints/last.ckpt 8192 2048
    .venv/bin/python scripts/time_render_chunks.py <run>/checkpoints/last.ckpt 2048 --scale 0.25
"""

import argparse
import time

from nerf_lightning.checkpoints import load_model, load_run_data


parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
parser.add_argument("ckpt")
parser.add_argument("chunks", type=int, nargs="+")
parser.add_argument("--scale", type=float, default=1.0)
args = parser.parse_args()
model, info = load_model(args.ckpt)
views = load_run_data(info["config"]).scene.held_out("test")
rendered = views.scaled(args.scale)
for chunk in args.chunks * 2:
    model.chunk_size = chunk
    started = time.perf_counter()
    model.render_view(rendered.K[0], rendered.c2w[0], rendered.height, rendered.width)
    seconds = time.perf_counter() - started
    full = f" ({seconds / args.scale**2:.0f} s a {views.width}x{views.height} frame at this rate)" if args.scale != 1.0 else ""
    print(f"chunk_size={chunk}: {seconds:.1f} s for {rendered.width}x{rendered.height}{full}", flush=True)
