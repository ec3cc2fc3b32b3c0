"""Instant-NGP's sample budget for the fixed-shape GPU presets (``callbacks.ray_budget``): a Lightning callback that
sizes the rays of the next steps from what an earlier step's rays wanted of the sampler's samples a step
(``model/sampler=fixed_shape_grid``'s ``samples_per_step``)."""

from __future__ import annotations

from typing import Any

import lightning as L
import torch


class RayBudget(L.Callback):
    """Instant-NGP's sample budget: the rays of the next training steps sized so that their samples fill the
    sampler's fixed number of samples a step (``samples_per_step``), from what the rays of an earlier step wanted,
    read back a step late so that the device never waits for the host.

    After each step the model's ``rays_that_fit`` (a 0-d device tensor, :attr:`RaySamples.rays_that_fit
    <nerf_lightning.rendering.packed.RaySamples.rays_that_fit>`: how many rays of the samples a ray wanted the
    sampler's samples a step would hold) is copied to the host without waiting (pinned
    memory and a CUDA event); at the start of a later step, once the copy has landed, ``data.batch_size`` becomes
    ``fill`` times it, rounded down to a multiple of ``multiple`` (so that a compiled step sees few sizes) and kept
    within ``min_rays``..``max_rays``. Too many rays and the last are cut short (left out of the loss); too few and
    the samples are padding. Each batch's tensors are marked as of a varying size, so that a compiled step traces
    one graph for any ray count, not one a count. The ray count is kept in checkpoints, so a resumed run goes on
    with it.

    Args:
        fill: the share of the samples a step to aim at: below 1, a step whose rays want more than the last's still fits.
        min_rays, max_rays, multiple: the bounds of the ray count, and its step. The march's table of steps is
            (rays, reach / step size): ``max_rays`` bounds its memory (65 536 rays of 1040 steps: a few GB).

    On a GPU the step at which a count lands depends on timing, so two runs with a budget are not the same step for
    step (their quality is).
    """

    def __init__(self, fill: float = 0.9, min_rays: int = 1024, max_rays: int = 65_536, multiple: int = 1024) -> None:
        if not 0 < fill <= 1 or multiple < 1 or not multiple <= min_rays <= max_rays:
            raise ValueError(f"callbacks.ray_budget: expected 0 < fill <= 1 and multiple <= min_rays <= max_rays, got fill={fill}, "
                             f"multiple={multiple}, min_rays={min_rays}, max_rays={max_rays}")
        self.fill, self.min_rays, self.max_rays, self.multiple = fill, min_rays, max_rays, multiple
        self.rays: int | None = None
        self.pending: tuple[torch.Tensor, Any] | None = None

    def setup(self, trainer: L.Trainer, pl_module: L.LightningModule, stage: str) -> None:
        if stage != "fit":
            return
        sampler = getattr(pl_module, "sampler", None)
        if sampler is None or not hasattr(trainer.datamodule, "set_rays_per_batch"):
            raise ValueError(f"callbacks.ray_budget sizes the rays of a radiance field's ray batches; {type(pl_module).__name__} "
                             f"on {type(trainer.datamodule).__name__} has none: remove the callback (~callbacks.ray_budget)")
        if getattr(sampler, "samples_per_step", None) is None:
            raise ValueError("callbacks.ray_budget sizes the rays a step to fill the sampler's samples a step, and "
                             f"{type(sampler).__name__} takes as many as the rays have: use model/sampler=fixed_shape_grid "
                             "(as experiment=fast_blender_gpu does), or remove the callback (~callbacks.ray_budget)")

    def on_fit_start(self, trainer: L.Trainer, pl_module: L.LightningModule) -> None:
        # resumed: the ray count it had (the callback's state is restored before this hook, and the first batch is
        # drawn after it)
        if self.rays is not None:  # within this run's bounds, which may have changed (a lower max_rays after running out of memory)
            self.rays = self._bounded(self.rays)
            trainer.datamodule.set_rays_per_batch(self.rays)

    def on_train_batch_end(self, trainer: L.Trainer, pl_module: L.LightningModule, outputs: Any, batch: Any, batch_idx: int) -> None:
        fit = getattr(pl_module, "rays_that_fit", None)
        if fit is None or self.pending is not None:
            return
        if fit.device.type == "cuda":  # copied as the device gets there; read once the event says it has
            host = torch.empty((), dtype=fit.dtype, pin_memory=True)
            host.copy_(fit, non_blocking=True)
            event = torch.cuda.Event()
            event.record()
            self.pending = (host, event)
        else:  # a CPU, or a device without events (Apple's): in order with the host
            self.pending = (fit.detach().to("cpu", copy=True), None)

    def on_train_batch_start(self, trainer: L.Trainer, pl_module: L.LightningModule, batch: Any, batch_idx: int) -> None:
        for value in batch.values():  # the ray count a symbol of a compiled step, not a constant (no effect run plainly)
            if isinstance(value, torch.Tensor):
                torch._dynamo.maybe_mark_dynamic(value, 0)
        if self.pending is None:
            return
        host, event = self.pending
        if event is not None and not event.query():
            return  # not there yet: a later step looks again
        self.pending = None
        self.rays = self._bounded(int(self.fill * float(host.numpy())))  # the host's copy: no device op
        trainer.datamodule.set_rays_per_batch(self.rays)  # the batches drawn from now on (the next may be drawn already)

    def _bounded(self, rays: int) -> int:
        """``rays`` rounded down to a multiple of ``multiple`` and kept within ``min_rays``..``max_rays``."""
        return min(max(rays // self.multiple * self.multiple, self.min_rays), self.max_rays)

    def state_dict(self) -> dict[str, Any]:
        return {"rays": self.rays}

    def load_state_dict(self, state_dict: dict[str, Any]) -> None:
        self.rays = state_dict.get("rays")
