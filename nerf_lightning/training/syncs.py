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


# a tensor made from host data (``torch.tensor``/``torch.as_tensor`` of Python numbers or lists): made on the host and,
# where the code asks for a GPU, copied there from pageable memory, a copy that waits (CUDA reports it as a
# synchronizing call); on a CPU nothing tells where it was meant to go, hence HostSyncs(host_data=True)
HOST_DATA = "aten.lift_fresh (a tensor from host data)"


class HostSyncs(TorchDispatchMode):
    """A dispatch mode that counts, by op name, the ops that make the host wait (``WAITING_OPS``, and indexing with a
    boolean mask as ``aten.index (boolean)``); ``counts`` holds them once the ``with`` block has run.

    ``host_data``: also count every tensor made from host data (:data:`HOST_DATA`), on any device: on a GPU each one
    asked for there is a copy that waits, which no other op shows, so that a test on a CPU can say a step makes none
    (one a step did on a GPU: a batch's rays made with ``torch.as_tensor(1.0, device=...)``). Not a number assigned
    into a tensor (``x[..., -1] = 1.0``: the number lifted to a host tensor, then filled in, which on a GPU is a
    fill with the host's number, no copy); a tensor made from host data and then assigned in is taken for one too."""

    def __init__(self, host_data: bool = False) -> None:
        super().__init__()
        self.counts: Counter[str] = Counter()
        self.host_data = host_data
        self._lifted: list[torch.Tensor] = []  # the last few tensors made from host data (an assignment's value?)

    def __torch_dispatch__(self, func: Any, types: Any, args: tuple = (), kwargs: dict | None = None) -> Any:
        name = f"aten.{func.__name__.split('.')[0]}"
        if name in WAITING_OPS and not (name == "aten.repeat_interleave" and (kwargs or {}).get("output_size") is not None):
            self.counts[name] += 1
        elif _is_boolean_index(func, args):
            self.counts[f"{name} (boolean)"] += 1
        elif self.host_data and name == "aten.lift_fresh":
            self.counts[HOST_DATA] += 1
            out = func(*args, **(kwargs or {}))
            self._lifted = [*self._lifted[-3:], out]
            return out
        elif self.host_data and self._lifted and name in ("aten.fill_", "aten.copy_", "aten.index_put_", "aten._index_put_impl_"):
            value = args[2] if name.endswith("index_put_") and len(args) > 2 else args[1] if len(args) > 1 else None
            if any(value is lifted for lifted in self._lifted):  # a number assigned into a tensor: not counted (see the class)
                self._lifted = [lifted for lifted in self._lifted if lifted is not value]
                self.counts[HOST_DATA] -= 1
                if not self.counts[HOST_DATA]:
                    del self.counts[HOST_DATA]
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
    (``on_before_backward``, which reads the loss back); ``host_data`` counts tensors made from host data too
    (:class:`HostSyncs`; for a count on a CPU):
    ``+callbacks.syncs={_target_: nerf_lightning.training.syncs.CountHostSyncs, path: syncs.json}``.

    On CUDA it also counts what CUDA itself reports as a synchronizing call (``torch.cuda.set_sync_debug_mode``,
    under ``cuda (synchronizing call)``): copies between the host and the device too, which no aten op names.
    While a dispatch mode is on, ``torch.compile`` runs the function as written, so with ``model.compile=true`` the
    count is of the plain step (the ops the compiled graph runs too)."""

    def __init__(self, path: str | None = None, skip_nan_guard: bool = False, host_data: bool = False) -> None:
        self.path, self.skip_nan_guard, self.host_data = path, skip_nan_guard, host_data
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
        self._mode = HostSyncs(self.host_data)
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
