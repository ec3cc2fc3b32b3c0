"""Counting the PyTorch operators a training step dispatches: each one that does work is at least one kernel launch
on a GPU, so the count bounds how much of a small step a GPU spends waiting on Python, and it can be measured (and
kept by a test) on a CPU, where no GPU is lent.

:class:`OperatorCount` is a ``TorchDispatchMode`` that counts every ATen operator below autograd (forward, backward
and the optimiser's update alike) except those that launch nothing: views and reshapes (``OpOverload.is_view``) and
the allocations, detaches and metadata changes in :data:`NO_LAUNCH`. :class:`StepOperatorCounter` counts the steps
of a Lightning fit from ``on_train_batch_start`` to ``on_train_batch_end``.
"""

from __future__ import annotations

import json
from collections import Counter
from typing import Any

import lightning as L
import torch
from torch.utils._python_dispatch import TorchDispatchMode

from nerf_lightning.io import write_atomic

# operators that allocate, alias or change metadata without running a kernel
NO_LAUNCH = frozenset({
    "empty", "empty_like", "empty_strided", "new_empty", "new_empty_strided", "detach", "alias", "lift_fresh",
    "resize_", "set_", "_reshape_alias", "sym_size", "sym_stride", "sym_numel", "sym_storage_offset", "is_same_size",
    "_has_compatible_shallow_copy_type", "is_nonzero", "_unsafe_view", "result_type",
    "_record_function_enter_new", "_record_function_exit",  # the profiler's labels
})


def launches(func: torch._ops.OpOverload) -> bool:
    """Whether ``func`` runs a kernel (not a view, reshape, allocation or metadata change)."""
    return not (func.is_view or func.overloadpacket.__name__ in NO_LAUNCH)


class OperatorCount(TorchDispatchMode):
    """Counts the operators dispatched while it is entered, by name (``counts``), those of :func:`launches` only."""

    def __init__(self) -> None:
        super().__init__()
        self.counts: Counter[str] = Counter()

    def __torch_dispatch__(self, func: Any, types: Any, args: tuple = (), kwargs: dict | None = None) -> Any:
        if launches(func):
            self.counts[func.overloadpacket.__name__] += 1
        return func(*args, **(kwargs or {}))


class StepOperatorCounter(L.Callback):
    """Counts the operators of training steps ``first`` to ``last`` (1-based, inclusive): forward, backward, the
    optimiser's update and the model's hooks in between (not the model's own ``on_train_batch_end``, which Lightning
    calls after the callbacks': a splat strategy's refinement every so many steps). ``per_step`` (name -> mean count a step) and ``total``
    (the mean a step) when they are done; with ``path``, written there as JSON at the end of training."""

    def __init__(self, first: int = 1, last: int = 24, path: str | None = None) -> None:
        if not 1 <= first <= last:
            raise ValueError(f"StepOperatorCounter needs 1 <= first <= last, got {first} and {last}")
        self.first, self.last, self.path = int(first), int(last), path
        self.steps: list[Counter[str]] = []
        self._mode: OperatorCount | None = None

    def on_train_batch_start(self, trainer: L.Trainer, pl_module: L.LightningModule, batch: Any, batch_idx: int) -> None:
        if self.first <= trainer.global_step + 1 <= self.last:
            self._mode = OperatorCount()
            self._mode.__enter__()

    def on_train_batch_end(self, trainer: L.Trainer, pl_module: L.LightningModule, outputs: Any, batch: Any, batch_idx: int) -> None:
        if self._mode is not None:
            self.steps.append(self._mode.counts)
            self._leave()

    @property
    def per_step(self) -> dict[str, float]:
        total: Counter[str] = Counter()
        for counts in self.steps:
            total.update(counts)
        return {name: count / max(len(self.steps), 1) for name, count in total.most_common()}

    @property
    def total(self) -> float:
        return sum(self.per_step.values())

    def on_exception(self, trainer: L.Trainer, pl_module: L.LightningModule, exception: BaseException) -> None:
        self._leave()

    def _leave(self) -> None:
        if self._mode is not None:  # training stopped inside a counted step
            self._mode.__exit__(None, None, None)
            self._mode = None

    def on_train_end(self, trainer: L.Trainer, pl_module: L.LightningModule) -> None:
        self._leave()
        if self.path is not None and trainer.is_global_zero:
            write_atomic(self.path, json.dumps({"steps": len(self.steps), "total": self.total, "per_step": self.per_step}).encode())
