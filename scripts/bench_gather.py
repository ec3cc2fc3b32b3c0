"""The hash grid's row gather on a CPU, three ways in one process, interleaved: ``gather_rows`` (rows of two float32
gathered as complex64 elements, the dense and the hashed levels' parts' gradients added into one buffer), the same
through autograd a part (``per_part_complex64``: a buffer for each part and one of the table's size for a slice, added
up; the code before 2c74162) and a plain ``index_select`` a part. Only the gather differs: the corner sums are the
encoding's own. Times the encoding at the presets' sizes (no grad, forward + backward) and, given a checkpoint, a
training step of its model (forward, backward and Adam on random rays of its training views) and a held-out frame at
half size. Medians, fixed seed, JSON out.

    .venv/bin/python scripts/bench_gather.py --ckpt <run>/checkpoints/last.ckpt --out docs/bench/hash_gather_parts_cpu.json

The ways alternate in blocks (ABC CBA ...), so that a machine whose speed drifts, as a shared VM's does, weighs on
all alike; a separate run of each, minutes apart, can differ by more than the gain. (docs/bench/hash_gather_cpu.json
is the two-way version of 2026-11-23.)
"""

from __future__ import annotations

import argparse
import json
import platform
import statistics
import sys
import time
from collections.abc import Callable
from pathlib import Path

import torch
import torch.nn.functional as F

import nerf_lightning.fields.hash_grid as hash_grid
from nerf_lightning.checkpoints import load_model, load_run_data
from nerf_lightning.geometry.rays import image_rays


sys.path.insert(0, str(Path(__file__).resolve().parent))
from bench_hash_grid import SIZES, encoding_calls  # noqa: E402  the presets' encodings, timed the same way



def per_part(complex64: bool) -> Callable[[torch.Tensor, list[torch.Tensor], list[int]], list[torch.Tensor]]:
    """``gather_rows`` as autograd does it a part: one ``index_select`` (as complex64 elements or not) on each part."""

    def gather(table: torch.Tensor, rows: list[torch.Tensor], starts: list[int]) -> list[torch.Tensor]:
        found = []
        for start, part in zip(starts, rows):
            if complex64 and table.shape[-1] == 2:
                found.append(torch.view_as_real(torch.index_select(torch.view_as_complex(table[start:]), 0, part)))
            else:
                found.append(torch.index_select(table[start:], 0, part))
        return found

    return gather


WAYS = {"one_buffer": hash_grid.gather_rows, "per_part_complex64": per_part(True), "per_part_index_select": per_part(False)}


def interleaved(function: Callable[[], object], ways: dict[str, Callable[[], None]], blocks: int, per_block: int) -> dict[str, float]:
    """Median seconds of ``function`` under each way (:func:`interleaved_seconds`)."""
    return {name: round(statistics.median(values), 4) for name, values in interleaved_seconds(function, ways, blocks, per_block).items()}


def interleaved_seconds(function: Callable[[], object], ways: dict[str, Callable[[], None]], blocks: int,
                        per_block: int) -> dict[str, list[float]]:
    """The seconds of each call of ``function`` under each way, ``blocks`` alternating blocks (ABBA...) of
    ``per_block`` calls after one warm-up call. ``ways`` maps a name to what switches the code to it; the first is
    switched back to at the end."""
    function()  # warm-up
    seconds: dict[str, list[float]] = {name: [] for name in ways}
    order = list(ways)
    for block in range(blocks):
        for name in order if block % 2 == 0 else order[::-1]:
            ways[name]()
            for _ in range(per_block):
                started = time.perf_counter()
                function()
                seconds[name].append(time.perf_counter() - started)
    ways[order[0]]()
    return seconds


def training_step_of(model: torch.nn.Module, train) -> Callable[[], None]:
    """A training step of ``model`` on 1024 random rays of the training views ``train``: forward, the sampler's
    losses against random colours, backward, Adam. The proposal networks learn on their schedule past the warm-up,
    as most steps do."""
    origins, directions = image_rays(train.K, train.c2w, train.height, train.width)  # (V, H, W, 3)
    cameras = torch.arange(len(train))[:, None, None].expand(origins.shape[:3]).reshape(-1)
    origins, directions = origins.reshape(-1, 3), directions.reshape(-1, 3)
    optimizer = torch.optim.Adam(model.parameters(), lr=1e-3, eps=1e-15)
    steps = iter(range(10**9))

    def training_step() -> None:
        rays = torch.randint(0, len(origins), (1024,))
        model.sampler.update(1000 + next(steps), model.field)
        out = model.render(origins[rays], directions[rays], perturb=True, camera_indices=cameras[rays])
        target = torch.rand(1024, 3)
        loss = F.mse_loss(out["rgb"], target) + sum(model.sampler.losses(out["samples"], out, target).values())
        optimizer.zero_grad()
        loss.backward()
        optimizer.step()

    return training_step


def time_encodings(ways: dict[str, Callable[[], None]], result: dict) -> None:
    """Into ``result``: the presets' encodings (``bench_hash_grid.SIZES``), no grad and forward + backward, 8 blocks
    of 3 under each way."""
    for name, options, n_points in SIZES:
        no_grad, _, forward_backward = encoding_calls(options, n_points)  # no grad as written: the compiled one gathers its own way
        result["seconds_median"][f"{name}_no_grad"] = interleaved(no_grad, ways, 8, 3)
        result["seconds_median"][f"{name}_forward_backward"] = interleaved(forward_backward, ways, 8, 3)
        print(name, {key: value for key, value in result["seconds_median"].items() if key.startswith(name)}, flush=True)


def time_all(ways: dict[str, Callable[[], None]], ckpt: Path | None, out: Path, result: dict) -> None:
    """The encodings and, given ``ckpt``, its training step and frame under each way, into ``result``, written to ``out``."""
    time_encodings(ways, result)
    if ckpt is not None:
        time_checkpoint(ckpt, ways, result)
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps(result, indent=2) + "\n")


def time_checkpoint(ckpt: Path, ways: dict[str, Callable[[], None]], result: dict) -> None:
    """Into ``result``: the checkpoint's training step (12 blocks of 5) and a held-out frame at half size (2 blocks
    of 1) under each way, the encodings' passes without gradients as written (``compile_evaluation`` off: the
    compiled one gathers its own way)."""
    model, info = load_model(ckpt)
    for module in model.modules():
        if hasattr(module, "compile_evaluation"):
            module.compile_evaluation = False
    result["checkpoint"] = str(ckpt.resolve())
    scene = load_run_data(info["config"]).scene
    model.train()
    result["seconds_median"]["training_step_1024_rays"] = interleaved(training_step_of(model, scene.train), ways, 12, 5)
    model.eval()
    views = scene.held_out("test").scaled(0.5)
    result["frame_size"] = [views.width, views.height]
    result["seconds_median"]["frame_half_size"] = interleaved(
        lambda: model.render_view(views.K[0], views.c2w[0], views.height, views.width), ways, 2, 1)
    print({key: result["seconds_median"][key] for key in ("training_step_1024_rays", "frame_half_size")}, flush=True)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--ckpt", type=Path, default=None, help="a proposal or hash-grid checkpoint: also time its training step and a frame")
    parser.add_argument("--out", type=Path, required=True)
    args = parser.parse_args()
    torch.manual_seed(0)
    ways = {name: (lambda gather=gather: setattr(hash_grid, "gather_rows", gather)) for name, gather in WAYS.items()}
    result = {"torch": torch.__version__, "threads": torch.get_num_threads(), "machine": platform.processor() or platform.machine(),
              "seconds_median": {}}
    time_all(ways, args.ckpt, args.out, result)


if __name__ == "__main__":
    main()
