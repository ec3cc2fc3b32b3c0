"""Milliseconds of the hash-grid encoding (nerf_lightning.fields.HashGridEncoding) on the CPU: the no-grad forward
(evaluation, the viewer) in plain PyTorch and compiled (``compile_evaluation``, the default; its first call, which
compiles, is the warm-up) and forward + backward (a training step's share) at the sizes the presets use, the best of 7
after a warm-up, fixed seed. Run it from another checkout (PYTHONPATH=<tree>) to compare two versions of the code.

    .venv/bin/python scripts/bench_hash_grid.py --out docs/bench/hash_grid_cpu.json
"""

from __future__ import annotations

import argparse
import json
import platform
import time
from collections.abc import Callable
from pathlib import Path

import torch

import nerf_lightning.fields.hash_grid as hash_grid

# (name, encoding options, points): a proposal network's grid on a 2048-ray chunk of 64 samples, the CPU presets'
# field on 2048 rays of 24 samples, and the GPU presets' 16 levels
SIZES = [("proposal_5_levels", dict(n_levels=5, log2_table_size=17, base_resolution=16, max_resolution=128), 131072),
         ("field_8_levels", dict(n_levels=8, log2_table_size=19, max_resolution=1024), 49152),
         ("field_16_levels", dict(n_levels=16, log2_table_size=19, max_resolution=2048), 100_000)]


def best_ms(function, repeats: int = 7) -> float:
    function()
    times = []
    for _ in range(repeats):
        started = time.perf_counter()
        function()
        times.append(time.perf_counter() - started)
    return round(min(times) * 1000.0, 1)


def encoding_calls(options: dict, n_points: int) -> tuple[Callable[[], None], Callable[[], None], Callable[[], None]]:
    """A ``HashGridEncoding(**options)`` and ``n_points`` random points -> the calls timed: its no-grad forward in
    plain PyTorch and compiled, and a forward + backward (into the table's gradient)."""
    encoding, points = hash_grid.HashGridEncoding(**options).eval(), torch.rand(n_points, 3)  # eval mode: as renders run it

    def no_grad(compiled: bool) -> Callable[[], None]:
        def forward() -> None:
            encoding.compile_evaluation = compiled
            with torch.no_grad():
                encoding(points)
        return forward

    def forward_backward() -> None:
        encoding.table.grad = None
        encoding(points).square().sum().backward()

    return no_grad(False), no_grad(True), forward_backward


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", type=Path, required=True)
    args = parser.parse_args()
    torch.manual_seed(0)
    result = {"code": hash_grid.__file__, "compile_failure": None, "torch": torch.__version__, "threads": torch.get_num_threads(), "machine": platform.processor() or platform.machine(), "sizes": {}}
    for name, options, n_points in SIZES:
        forward_no_grad, forward_compiled, forward_backward = encoding_calls(options, n_points)
        result["sizes"][name] = {"options": options, "points": n_points, "no_grad_ms": best_ms(forward_no_grad),
                                 "no_grad_compiled_ms": best_ms(forward_compiled), "forward_backward_ms": best_ms(forward_backward)}
        print(name, result["sizes"][name], flush=True)
    # not None: "compiled" ran plain PyTorch (this machine cannot compile, or older code without the compiled path)
    compiled = getattr(hash_grid, "_compiled_interpolation", None)
    result["compile_failure"] = compiled.failure if compiled is not None else "this code has no compiled evaluation"
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(result, indent=2) + "\n")


if __name__ == "__main__":
    main()
