"""Seconds to render held-out view 0 of a checkpoint's scene at several ``model.chunk_size`` values, each twice.

    .venv/bin/python scripts/time_render_chunks.py <run>/checkpoints/last.ckpt 8192 2048
"""

import sys
import time

from nerf_lightning.checkpoints import load_model, load_run_data
from nerf_lightning.rendering.views import render_view

model, info = load_model(sys.argv[1])
views = load_run_data(info["config"]).scene.held_out("test")
for chunk in [int(value) for value in sys.argv[2:]] * 2:
    model.chunk_size = chunk
    started = time.perf_counter()
    render_view(model, views.K[0], views.c2w[0], views.height, views.width)
    print(f"chunk_size={chunk}: {time.perf_counter() - started:.1f} s for {views.width}x{views.height}", flush=True)
