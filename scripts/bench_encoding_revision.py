"""The hash-grid encoding's ``forward`` of a git revision against the working tree's, interleaved in one process, on
a CPU: the presets' encodings (no grad, forward + backward) and, given a checkpoint, its training step and a held-out
frame at half size (as ``scripts/bench_gather.py`` times them). Medians, fixed seed, JSON out.

    .venv/bin/python scripts/bench_encoding_revision.py --rev 275503d --ckpt <run>/checkpoints/last.ckpt \
        --out docs/bench/hash_grid_complex_sum_cpu.json

Only ``HashGridEncoding.forward`` is swapped (with the module functions it calls, from the revision's file); the
class's other methods and buffers are the working tree's, so the two must agree on those.
"""

from __future__ import annotations

import argparse
import importlib.util
import platform
import subprocess
import sys
import tempfile
from pathlib import Path

import torch

import nerf_lightning.fields.hash_grid as hash_grid

sys.path.insert(0, str(Path(__file__).resolve().parent))
from bench_gather import time_all  # noqa: E402  the same encodings, blocks, training step and frame

ROOT = Path(__file__).resolve().parent.parent


def forward_at(revision: str):
    """``HashGridEncoding.forward`` as nerf_lightning/fields/hash_grid.py has it at ``revision``."""
    source = subprocess.run(["git", "show", f"{revision}:nerf_lightning/fields/hash_grid.py"], cwd=ROOT, check=True,
                            capture_output=True, text=True).stdout
    path = Path(tempfile.mkdtemp()) / "hash_grid_at_revision.py"
    path.write_text(source)
    spec = importlib.util.spec_from_file_location("hash_grid_at_revision", path)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module.HashGridEncoding.forward


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--rev", required=True, help="the git revision to compare the working tree with")
    parser.add_argument("--ckpt", type=Path, default=None, help="a proposal or hash-grid checkpoint: also time its training step and a frame")
    parser.add_argument("--out", type=Path, required=True)
    args = parser.parse_args()
    torch.manual_seed(0)
    forwards = {"working_tree": hash_grid.HashGridEncoding.forward, args.rev: forward_at(args.rev)}
    ways = {name: (lambda forward=forward: setattr(hash_grid.HashGridEncoding, "forward", forward)) for name, forward in forwards.items()}
    result = {"revision": args.rev, "torch": torch.__version__, "threads": torch.get_num_threads(),
              "machine": platform.processor() or platform.machine(), "seconds_median": {}}
    time_all(ways, args.ckpt, args.out, result)


if __name__ == "__main__":
    main()
