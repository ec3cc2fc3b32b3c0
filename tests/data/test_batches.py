"""The batches of a training step: drawn from a seed and the step, each rank its own."""

import torch

from nerf_lightning.data.batches import SegmentedBatches


def test_each_rank_draws_its_own_rays():
    def draw(generator):
        return torch.randint(0, 1_000_000, (8,), generator=generator)

    ranks = [next(iter(SegmentedBatches(draw, lambda: 0, lambda step: 1, seed=0, rank=lambda r=r: r))) for r in (0, 1)]
    assert not torch.equal(ranks[0], ranks[1])


def test_batches_for_a_cuda_device_are_pinned_so_their_copy_does_not_wait():
    # a copy from ordinary memory to a GPU makes the host wait for the device; from pinned memory Lightning's copy
    # (non_blocking) does not. Only the loader's flag is checked here: pinning itself needs CUDA
    from types import SimpleNamespace

    from nerf_lightning.data.batches import StepBatchesDataModule

    class Module(StepBatchesDataModule):
        def draw_batch(self, generator):
            return {"pixel_index": torch.randint(0, 10, (4,), generator=generator)}

    module = Module(batch_size=4, val_every=10)
    for device, pinned in (("cuda", True), ("cpu", False), ("mps", False)):
        module.trainer = SimpleNamespace(strategy=SimpleNamespace(root_device=torch.device(device)), global_step=0, global_rank=0, max_steps=10)
        assert module.train_dataloader().pin_memory is pinned, device
    module.trainer = None
    assert module.train_dataloader().pin_memory is False
