"""Training a model from a composed config with Lightning (what nerf-train runs); metrics.json in the run folder."""

from __future__ import annotations

import logging
import time
import warnings
from pathlib import Path
from typing import Any

import lightning as L
from hydra.utils import instantiate
from omegaconf import DictConfig, OmegaConf

from nerf_lightning.training.callbacks import RunConfigInCheckpoint, StepProgressBar
from nerf_lightning.checkpoints import checkpoint_globals, read_checkpoint
from nerf_lightning.devices import enable_tf32, peak_memory_gb, resolve_device
from nerf_lightning.errors import ensure_writable
from nerf_lightning.io import write_json

# Batches are drawn in the main process on purpose: workers would only copy the precomputed tensors.
warnings.filterwarnings("ignore", ".*does not have many workers.*")
warnings.filterwarnings("ignore", r".*isinstance\(treespec, LeafSpec\).*")
# Lightning's adverts for its cloud services (litlogger, litmodels) on every run; it has no switch for them (Lightning-AI/pytorch-lightning#21294)
logging.getLogger("lightning.pytorch.utilities.rank_zero").addFilter(lambda record: "💡 Tip" not in record.getMessage())


def accelerator_for(cfg: DictConfig, model: Any) -> dict[str, Any]:
    """What the trainer's ``accelerator`` (and ``devices``) becomes where the model trains elsewhere than
    ``trainer.accelerator=auto`` would put it (a model's ``device_for``: splats not on an Apple GPU); {} otherwise."""
    device_for = getattr(model, "device_for", None)
    if device_for is None or str(cfg.trainer.get("accelerator", "auto")) != "auto":
        return {}
    chosen = resolve_device("auto")
    moved = device_for(chosen, asked=False)
    return {} if moved == chosen else {"accelerator": moved.type, "devices": 1}


def train(cfg: DictConfig) -> dict[str, Any]:
    """Train the model ``cfg.model`` on ``cfg.data``; returns the final metrics also written to metrics.json."""
    output_dir = ensure_writable(cfg.paths.output_dir, "paths.output_dir")
    ckpt_path = cfg.get("ckpt_path")
    if ckpt_path:
        if not Path(ckpt_path).expanduser().is_file():
            raise FileNotFoundError(f"ckpt_path={ckpt_path} not found: expected a checkpoint of a run, such as <run>/checkpoints/last.ckpt")
        # refuses, in one line, a checkpoint of an older layout, or one that would run code, before Lightning reads it
        read_checkpoint(ckpt_path, trust=cfg.trust_checkpoint)
    L.seed_everything(cfg.seed, workers=True, verbose=False)
    enable_tf32()

    datamodule = instantiate(cfg.data)
    model = instantiate(cfg.model)
    resolved = OmegaConf.to_container(cfg, resolve=True)
    callbacks = [instantiate(callback) for callback in (cfg.get("callbacks") or {}).values()]
    callbacks.append(RunConfigInCheckpoint(resolved))
    if cfg.trainer.get("enable_progress_bar", True):
        callbacks.append(StepProgressBar())
    loggers = [instantiate(logger) for logger in (cfg.get("logger") or {}).values()]
    trainer: L.Trainer = instantiate(cfg.trainer, callbacks=callbacks, logger=loggers or False, **accelerator_for(cfg, model))

    started = time.perf_counter()
    with checkpoint_globals():  # Lightning reads the checkpoint again: as strictly as we did
        trainer.fit(model, datamodule=datamodule, ckpt_path=ckpt_path, weights_only=not cfg.trust_checkpoint)
    wall_seconds = time.perf_counter() - started

    metrics: dict[str, Any] = {key: float(value) for key, value in trainer.callback_metrics.items()}
    metrics.update(step=int(trainer.global_step), wall_seconds=round(wall_seconds, 3))
    peak = peak_memory_gb(trainer.strategy.root_device)
    if peak is not None:  # on CUDA: the run's peak of allocated GPU memory (nerf-bench's results carry it)
        metrics["peak_memory_gb"] = peak
    if trainer.is_global_zero:
        write_json(output_dir / "metrics.json", metrics)
    return metrics
