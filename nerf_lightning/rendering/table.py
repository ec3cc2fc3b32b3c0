"""The table renderer (``model/renderer=table``, the GPU presets): every sample laid out on a table (a sampler's of a
fixed number a ray, as the proposal sampler's) rendered in one pass, so that no size in a training step depends on
the data and the host never waits for the device."""

from __future__ import annotations

from typing import TYPE_CHECKING

from nerf_lightning.rendering.packed import RaySamples
from nerf_lightning.rendering.rounds import RoundsRenderer

if TYPE_CHECKING:
    from nerf_lightning.rendering.samplers.base import RaySampler


class TableRenderer(RoundsRenderer):
    """The rounds renderer that composites every sample on a table (:attr:`RaySamples.slots
    <nerf_lightning.rendering.packed.RaySamples.slots>`) in one pass (:meth:`RoundsRenderer.one_pass
    <nerf_lightning.rendering.rounds.RoundsRenderer.one_pass>`), not only those of a fixed shape: every field
    evaluation of a proposal sampler's step in one, where the rounds would read back which rays are alive.

    What the samples say decides: samples without a table (an occupancy grid's, which vary with the rays) are
    rendered in rounds, with ``early_stop_eps`` and ``samples_per_round``.
    """

    def in_one_pass(self, samples: RaySamples) -> bool:
        return samples.slots is not None

    def steps_in_one_pass(self, sampler: RaySampler) -> bool:
        return sampler.samples_on_table or super().steps_in_one_pass(sampler)

    def __repr__(self) -> str:
        return f"TableRenderer(every table in one pass; others: {super().__repr__()})"
