"""The batches of a training step: drawn from a seed and the step, each rank its own."""

import torch

from nerf_lightning.data.batches import SegmentedBatches


def test_each_rank_draws_its_own_rays():
    def draw(generator):
        return torch.randint(0, 1_000_000, (8,), generator=generator)

    ranks = [next(iter(SegmentedBatches(draw, lambda: 0, lambda step: 1, seed=0, rank=lambda r=r: r))) for r in (0, 1)]
    assert not torch.equal(ranks[0], ranks[1])
