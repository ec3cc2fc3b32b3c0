"""Where the callbacks lived before they moved beside what they serve (kept so that configs and code written for
0.3 keep working; each name warns once and says where it lives now):

| was | now |
|---|---|
| ``nerf_lightning.callbacks.Snapshots``, ``StepOrTimeCheckpoint``, ``RunConfigInCheckpoint``, ``StepProgressBar``, ``TimedCallback``, ``TrainingClock``, ``history_psnr`` | ``nerf_lightning.training.callbacks`` |
| ``nerf_lightning.callbacks.LiveViewer`` | ``nerf_lightning.viz.live.LiveViewer`` |
| ``nerf_lightning.callbacks.RayBudget`` | ``nerf_lightning.models.ray_budget.RayBudget`` |
"""

from __future__ import annotations

import importlib
import warnings
from typing import Any

MOVED = {
    **{name: "nerf_lightning.training.callbacks" for name in (
        "Snapshots", "StepOrTimeCheckpoint", "RunConfigInCheckpoint", "StepProgressBar", "TimedCallback", "TrainingClock",
        "history_psnr")},
    "LiveViewer": "nerf_lightning.viz.live",
    "RayBudget": "nerf_lightning.models.ray_budget",
}


def __getattr__(name: str) -> Any:
    if name not in MOVED:
        raise AttributeError(f"module 'nerf_lightning.callbacks' has no attribute {name!r}")
    warnings.warn(f"nerf_lightning.callbacks.{name} is now {MOVED[name]}.{name}: write that (in a config's _target_ too)",
                  FutureWarning, stacklevel=2)
    return getattr(importlib.import_module(MOVED[name]), name)
