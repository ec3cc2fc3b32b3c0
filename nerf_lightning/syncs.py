"""Counting the operations that make the host wait for a GPU: a value read back (``.item()``, ``int()``, ``bool()``
of a device tensor), a size that depends on the data (``nonzero``, a boolean mask's index, ``masked_select``). On a
GPU each one stops Python until every kernel queued before it has run, so a training step with none of them keeps
the device busy while Python queues the next step. They are counted on any device (the CPU included), so a test
needs no GPU to say that a step has none.

    with HostSyncs() as syncs:
        loss = model.training_step(batch, 0)
        loss.backward()
    syncs.counts  # {"aten.nonzero": 2, ...}
"""

from __future__ import annotations

import warnings
from collections import Counter
from pathlib import Path
from typing import Any

import lightning as L
import torch
from torch.utils._python_dispatch import TorchDispatchMode

from nerf_lightning.io import write_json

# the ops whose result the host must wait for (a value, or a size that depends on the values)
WAITING_OPS = {
    "aten._local_scalar_dense": "a value read back (.item(), int(), float(), bool() of a tensor)",
    "aten.nonzero": "nonzero without a size",
    "aten.masked_select": "a boolean mask's selection",
    "aten.is_nonzero": "bool() of a tensor",
    "aten.item": "item()",
    "aten.unique": "unique",
    "aten._unique2": "unique",
    "aten.bincount": "bincount (its size depends on the largest value)",
    "aten.repeat_interleave": "repeat_interleave without output_size",
}


def _is_boolean_index(func: Any, args: tuple) -> bool:
    """``x[mask]`` (aten.index with a bool index), whose size depends on the mask's values."""
    if func.__name__.split(".")[0] not in ("index", "index_put", "index_put_", "_index_put_impl_"):
        return False
    indices = args[1] if len(args) > 1 else ()
    return any(isinstance(index, torch.Tensor) and index.dtype == torch.bool for index in indices or ())


class HostSyncs(TorchDispatchMode):
    """A dispatch mode that counts, by op name, the ops that make the host wait (``WAITING_OPS``, and indexing with a
    boolean mask as ``aten.index (boolean)``); ``counts`` holds them once the ``with`` block has run."""

    def __init__(self) -> None:
        super().__init__()
        self.counts: Counter[str] = Counter()

    def __torch_dispatch__(self, func: Any, types: Any, args: tuple = (), kwargs: dict | None = None) -> Any:
        name = f"aten.{func.__name__.split('.')[0]}"
        if name in WAITING_OPS and not (name == "aten.repeat_interleave" and (kwargs or {}).get("output_size") is not None):
            self.counts[name] += 1
        elif _is_boolean_index(func, args):
            self.counts[f"{name} (boolean)"] += 1
        return func(*args, **(kwargs or {}))

    @property
    def total(self) -> int:
        return sum(self.counts.values())



class CountHostSyncs(L.Callback):
    """A Lightning callback counting :class:`HostSyncs` a training step into ``steps``, one Counter a step, and
    writing them to ``path`` (a JSON list) when training ends. A step counts from its ``on_train_batch_start`` to
    the next step's: its forward, backward and optimiser step, and also what Lightning and every callback do around
    it (logging, the progress bar, drawing the next batch), which wait for the device as much as the step itself;
    a validation ends the step before it. ``skip_nan_guard`` turns the model's NaN guard off
    (``on_before_backward``, which reads the loss back):
    ``+callbacks.syncs={_target_: nerf_lightning.syncs.CountHostSyncs, path: syncs.json}``.

    On CUDA it also counts what CUDA itself reports as a synchronizing call (``torch.cuda.set_sync_debug_mode``,
    under ``cuda (synchronizing call)``): copies between the host and the device too, which no aten op names.
    While a dispatch mode is on, ``torch.compile`` runs the function as written, so with ``model.compile=true`` the
    count is of the plain step (the ops the compiled graph runs too)."""

    def __init__(self, path: str | None = None, skip_nan_guard: bool = False) -> None:
        self.path, self.skip_nan_guard = path, skip_nan_guard
        self.steps: list[Counter[str]] = []
        self._mode: HostSyncs | None = None
        self._cuda_warnings: warnings.catch_warnings | None = None
        self._caught: list[warnings.WarningMessage] = []

    def setup(self, trainer: L.Trainer, pl_module: L.LightningModule, stage: str) -> None:
        if self.skip_nan_guard:  # to count the rest: the guard reads the loss back (every step on a CPU)
            pl_module.on_before_backward = lambda loss: None

    def _end_step(self) -> None:
        if self._mode is not None:
            self._mode.__exit__(None, None, None)
            if self._cuda_warnings is not None:
                torch.cuda.set_sync_debug_mode(0)
                self._cuda_warnings.__exit__(None, None, None)
                reported = [warning for warning in self._caught if "synchroniz" in str(warning.message)]
                if reported:
                    self._mode.counts["cuda (synchronizing call)"] += len(reported)
                for warning in self._caught:  # the run's other warnings, passed on as they came
                    if warning not in reported:
                        warnings.warn_explicit(warning.message, warning.category, warning.filename, warning.lineno)
                self._cuda_warnings = None
            self.steps.append(self._mode.counts)
            self._mode = None

    def on_train_batch_start(self, trainer: L.Trainer, pl_module: L.LightningModule, batch: Any, batch_idx: int) -> None:
        self._end_step()
        self._mode = HostSyncs()
        self._mode.__enter__()
        if pl_module.device.type == "cuda":  # CUDA's own report of every call that waits, copies included
            self._cuda_warnings = warnings.catch_warnings(record=True)
            self._caught = self._cuda_warnings.__enter__()
            warnings.simplefilter("always")
            torch.cuda.set_sync_debug_mode("warn")

    def on_validation_start(self, trainer: L.Trainer, pl_module: L.LightningModule) -> None:
        self._end_step()

    def on_train_end(self, trainer: L.Trainer, pl_module: L.LightningModule) -> None:
        self._end_step()
        if self.path is not None:
            write_json(Path(self.path), [dict(counts) for counts in self.steps])

    def on_exception(self, trainer: L.Trainer, pl_module: L.LightningModule, exception: BaseException) -> None:
        self._end_step()
