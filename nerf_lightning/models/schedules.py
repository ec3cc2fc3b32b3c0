"""Learning-rate schedules built from the run's step budget."""

from __future__ import annotations

import torch


def exponential_decay(optimizer: torch.optim.Optimizer, final_ratio: float, steps: int) -> torch.optim.lr_scheduler.ExponentialLR:
    """Multiply the learning rate by ``final_ratio`` over ``steps`` steps, smoothly (NeRF's decay)."""
    if steps <= 0 or final_ratio <= 0:
        raise ValueError(f"exponential_decay needs steps > 0 and final_ratio > 0, got {steps}, {final_ratio}")
    return torch.optim.lr_scheduler.ExponentialLR(optimizer, gamma=final_ratio ** (1.0 / steps))
