"""The benchmark runner's callbacks: checkpoints at training minutes and a stop after a training-time budget."""

from __future__ import annotations

import json

import lightning as L
import pytest
import torch
from hydra.utils import instantiate

from nerf_lightning.bench.callbacks import CheckpointAtMinutes, StopAtTrainingMinutes
from tests.test_experiments import tiny_data, tiny_overrides  # noqa: F401 (tiny_data is a fixture)


def fit(cfg, callback: L.Callback) -> L.Trainer:
    """Train ``cfg`` as nerf-train does (seeded alike), with ``callback`` watching."""
    L.seed_everything(cfg.seed, workers=True, verbose=False)
    trainer = instantiate(cfg.trainer, callbacks=[callback], logger=False, enable_checkpointing=False)
    trainer.fit(instantiate(cfg.model), datamodule=instantiate(cfg.data))
    return trainer


def test_checkpoints_at_training_minutes(tiny_data, make_config, scene_cache, monkeypatch, tmp_path):
    """A mark reached during training gets that step's weights; one training never reaches, the last weights."""
    monkeypatch.setenv("NERF_LIGHTNING_CACHE", str(scene_cache))
    marks = CheckpointAtMinutes(str(tmp_path / "marks"), minutes=[60.0, 1e-6])
    trainer = fit(make_config(*tiny_overrides("fast", tiny_data), "data.val_every=null", "trainer.max_steps=3"), marks)
    listed = json.loads((tmp_path / "marks" / "marks.json").read_text())
    assert [(m["minutes"], m["step"]) for m in listed] == [(1e-6, 1), (60.0, trainer.global_step)]
    assert torch.load(tmp_path / "marks" / "minute_1e-06.ckpt", weights_only=False)["global_step"] == 1
    with pytest.raises(ValueError, match="minutes"):
        CheckpointAtMinutes(str(tmp_path), minutes=[0])


def test_training_stops_at_training_minutes(tiny_data, make_config, scene_cache, monkeypatch):
    """The first step takes longer than 1e-6 minutes of training: the run stops after it, not at max_steps."""
    monkeypatch.setenv("NERF_LIGHTNING_CACHE", str(scene_cache))
    trainer = fit(make_config(*tiny_overrides("fast", tiny_data), "data.val_every=null", "trainer.max_steps=5"), StopAtTrainingMinutes(1e-6))
    assert trainer.global_step == 1
    with pytest.raises(ValueError, match="minutes"):
        StopAtTrainingMinutes(0)
