"""What the micro-benchmarks in ``scripts/`` share (``bench_hash_encoding.py``, ``bench_train_step.py``,
``bench_frame.py``, ``bench_process_data.py``): their common arguments, fixed seeds, a timer that warms up, then
times repeats and gives the median and the spread (waiting for a GPU at each mark), a clean skip where the data is
missing, the callback that times the library's own training steps, and the JSON every one of them writes: the
machine, versions, revision and date (:func:`~nerf_lightning.bench.machine.provenance`) and the exact command line
first, then the figures.

The end-to-end benchmarks (a preset on a scene for so many minutes, PSNR against time) are ``nerf-bench``'s.
"""

from __future__ import annotations

import argparse
import json
import math
import random
import statistics
import sys
import time
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any, NoReturn

import lightning as L
import numpy as np
import torch
from omegaconf import DictConfig, OmegaConf

from nerf_lightning.bench.machine import provenance
from nerf_lightning.devices import DEVICE_CHOICES, resolve_device, synchronize
from nerf_lightning.io import write_atomic

# the checkout's root and the data folder beside it (../shared/data), where the scripts find their default scenes
REPOSITORY = Path(__file__).resolve().parents[2]
SHARED_DATA = REPOSITORY.parent / "shared" / "data"
# a scene a preset's loader reads when no --root is given: data.scene's loader -> a folder of SHARED_DATA
DEFAULT_SCENES = {"load_blender": "nerf_synthetic/lego", "load_llff": "nerf_llff_data/fern", "load_transforms": "nerfstudio/fox"}


# -- arguments, seeds, devices -------------------------------------------------------------------------------------

def add_common_arguments(parser: argparse.ArgumentParser, *, warmup: int = 1, repeats: int | None = 5, device: bool = True) -> None:
    """``--warmup`` and ``--repeats`` (of :func:`time_call`; None: no ``--repeats``), ``--seed``, ``--out`` and, with
    ``device``, ``--device``."""
    parser.add_argument("--warmup", type=int, default=warmup, help=f"untimed runs first (default {warmup})")
    if repeats is not None:
        parser.add_argument("--repeats", type=int, default=repeats, help=f"timed runs (default {repeats})")
    parser.add_argument("--seed", type=int, default=0, help="seeds torch, numpy and random (default 0)")
    parser.add_argument("--out", type=Path, default=None, help="also write the JSON here")
    if device:
        parser.add_argument("--device", default="auto", help=f"{DEVICE_CHOICES} (default auto: a GPU where there is one)")


def parse_device(name: str) -> torch.device:
    """``--device`` as a torch device; exits with one line (status 1) for one this machine lacks."""
    try:
        return resolve_device(name)
    except ValueError as error:
        raise SystemExit(f"--device: {error}") from None


def seed_everything(seed: int) -> None:
    """Seed Python's, numpy's and torch's generators (every device's)."""
    random.seed(seed)
    np.random.seed(seed)
    torch.manual_seed(seed)


# -- timing --------------------------------------------------------------------------------------------------------

def summarize(seconds: Sequence[float]) -> dict[str, Any]:
    """Median, mean, min, max, standard deviation and interquartile range of ``seconds`` (each ``_s``), how many
    (``repeats``) and all of them (``all_s``). ValueError for none."""
    values = [float(value) for value in seconds]
    if not values:
        raise ValueError("summarize needs at least one time")
    quartiles = statistics.quantiles(values, n=4, method="inclusive") if len(values) > 1 else [values[0]] * 3
    return {
        "median_s": statistics.median(values), "mean_s": statistics.fmean(values), "min_s": min(values), "max_s": max(values),
        "stdev_s": statistics.stdev(values) if len(values) > 1 else 0.0, "iqr_s": quartiles[2] - quartiles[0],
        "repeats": len(values), "all_s": [round(value, 7) for value in values],
    }


def time_call(function: Callable[[], Any], repeats: int = 5, warmup: int = 1, device: torch.device | str | None = None,
              clock: Callable[[], float] = time.perf_counter) -> dict[str, Any]:
    """Call ``function`` ``warmup`` times untimed, then ``repeats`` times timed: :func:`summarize` of the timed calls,
    with ``warmup_s``, the warm-up calls' seconds (a first call that compiles shows there). On a GPU ``device``
    (CUDA, MPS) the device is waited for before each call starts and after it ends, so a time counts the work the
    call queued, not only its launch."""
    if repeats < 1 or warmup < 0:
        raise ValueError(f"time_call needs repeats >= 1 and warmup >= 0, got {repeats} and {warmup}")
    device = None if device is None else torch.device(device)

    def once() -> float:
        if device is not None:
            synchronize(device)
        started = clock()
        function()
        if device is not None:
            synchronize(device)
        return clock() - started

    warm = [once() for _ in range(warmup)]
    result = summarize([once() for _ in range(repeats)])
    result["warmup_s"] = [round(value, 7) for value in warm]
    return result


class StepTimer(L.Callback):
    """Times the training steps of a Lightning fit after the first ``warmup_steps``: ``step_s``, from
    ``on_train_batch_start`` to ``on_train_batch_end`` (the training step: forward, losses, backward, optimiser step;
    the batch already drawn), and ``loop_s``, from one step's end to the next's (the whole loop: drawing the batch,
    Lightning's bookkeeping). On a GPU it waits for the device at each mark. With ``path``, it writes both lists and
    the device there when training ends (for a fit run through :func:`nerf_lightning.training.train`, which builds
    its callbacks from the config: ``+callbacks.step_timer={_target_: nerf_lightning.bench.micro.StepTimer, ...}``)."""

    def __init__(self, warmup_steps: int = 5, path: str | None = None) -> None:
        if warmup_steps < 0:
            raise ValueError(f"StepTimer.warmup_steps must be >= 0, got {warmup_steps}")
        self.warmup_steps, self.path = int(warmup_steps), path
        self.step_s: list[float] = []
        self.loop_s: list[float] = []
        self.device: str | None = None
        self._started: float | None = None
        self._last_end: float | None = None

    def _mark(self, pl_module: L.LightningModule) -> float:
        synchronize(pl_module.device)
        return time.perf_counter()

    def on_train_batch_start(self, trainer: L.Trainer, pl_module: L.LightningModule, batch: Any, batch_idx: int) -> None:
        self.device = str(pl_module.device)
        self._started = self._mark(pl_module)

    def on_train_batch_end(self, trainer: L.Trainer, pl_module: L.LightningModule, outputs: Any, batch: Any, batch_idx: int) -> None:
        ended = self._mark(pl_module)
        step = trainer.global_step - 1  # steps done before this one (global_step counts this one by now)
        if step >= self.warmup_steps and self._started is not None:
            self.step_s.append(ended - self._started)
            if self._last_end is not None:
                self.loop_s.append(ended - self._last_end)
        self._last_end = ended

    def on_train_end(self, trainer: L.Trainer, pl_module: L.LightningModule) -> None:
        if self.path is not None and trainer.is_global_zero:
            write_atomic(self.path, json.dumps({"device": self.device, "warmup_steps": self.warmup_steps, "step_s": self.step_s,
                                                "loop_s": self.loop_s}).encode())


# -- configs and data ----------------------------------------------------------------------------------------------

def default_root(cfg: DictConfig) -> Path | None:
    """The scene of ``../shared/data`` for a preset whose ``data.root`` is still to be given (``???``): lego for a
    Blender loader, fern for LLFF, fox for a transforms.json capture; None where the data needs no root (the
    procedural scene, an image) or the loader has no default here."""
    if not OmegaConf.is_missing(cfg.data, "root"):
        return None
    loader = str(OmegaConf.select(cfg, "data.scene._target_", default="")).rsplit(".", 1)[-1]
    return SHARED_DATA / DEFAULT_SCENES[loader] if loader in DEFAULT_SCENES else None


def compose_preset(preset: str, overrides: Sequence[str] = (), root: Path | None = None, output_dir: str | Path | None = None,
                   need_data: bool = True) -> tuple[DictConfig, Path | None]:
    """``experiment=<preset>`` with Hydra ``overrides`` (:func:`~nerf_lightning.config.compose_config`, as ``nerf-train``
    composes it) and the folder of its data: ``data.root`` where the overrides set it, else ``root``, else the
    preset's scene in ``../shared/data`` (:func:`default_root`); None for data that needs no root (the procedural
    scene). With ``need_data``, :func:`skip` when that folder is missing; without, the root is left as the preset
    has it (for a benchmark that reads only the model's settings)."""
    from nerf_lightning.config import compose_config

    base = [f"experiment={preset}", *overrides, f"paths.output_dir={output_dir or '/tmp/nerf_bench_unused'}"]
    cfg = compose_config(base)
    if "root" not in cfg.data.keys():  # keys(): `in` leaves out a key whose value is missing (???)
        if root is not None:
            raise SystemExit(f"--root: experiment={preset} reads no data.root (its scene is built in, or its data is data.path)")
        return cfg, None
    missing = OmegaConf.is_missing(cfg.data, "root")
    if not missing and cfg.data.root is not None:
        given = Path(str(cfg.data.root)).expanduser()
        if need_data:
            require_path(given)
        return cfg, given
    root = root or default_root(cfg)
    if root is None:
        if need_data and missing:
            raise SystemExit(f"experiment={preset} needs a data.root: give --root")
        return cfg, None
    if need_data:
        require_path(root.expanduser())
    root = root.expanduser().resolve()
    return compose_config([*base, f"data.root={root}"]), root


# -- results -------------------------------------------------------------------------------------------------------

def skip(reason: str) -> NoReturn:
    """Print ``{"skipped": reason}`` and exit 0: what a benchmark does where its data (or an optional package) is missing."""
    print(json.dumps({"skipped": reason}))
    raise SystemExit(0)


def require_path(path: Path, what: str = "data") -> Path:
    """``path`` if it exists, else :func:`skip` naming it."""
    if not Path(path).expanduser().exists():
        skip(f"{what} not found: {path}")
    return Path(path)


def start_result(device: torch.device | str = "auto") -> dict[str, Any]:
    """The head of every micro-benchmark's JSON: :func:`~nerf_lightning.bench.machine.provenance` of ``device`` and the
    exact command line (``command``: ``sys.argv`` as given)."""
    return {**provenance(str(device)), "command": list(sys.argv)}


def finite_json(value: Any) -> Any:
    """``value`` with every float that is not finite (NaN, inf) made None, so the JSON stays standard."""
    if isinstance(value, float) and not math.isfinite(value):
        return None
    if isinstance(value, dict):
        return {key: finite_json(item) for key, item in value.items()}
    if isinstance(value, (list, tuple)):
        return [finite_json(item) for item in value]
    return value


def finish(result: dict[str, Any], out: Path | None) -> str:
    """Print ``result`` as JSON and, given ``out``, write it there (folders made); returns the text."""
    text = json.dumps(finite_json(result), indent=2)
    print(text, flush=True)
    if out is not None:
        write_atomic(out, (text + "\n").encode())
    return text
