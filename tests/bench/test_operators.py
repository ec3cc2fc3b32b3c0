"""The operator count of a splat training step (nerf_lightning.bench.operators): what it counts, and the step's
budget, so that the GPU preset's step stays a few launches (issue 73: 197 operators a step before, 70 at most)."""

from __future__ import annotations

import torch

from nerf_lightning.bench.operators import OperatorCount, StepOperatorCounter
from nerf_lightning.training import train

# the budget of operators a splat_blender_gpu step may dispatch (forward, backward, the optimiser's update, the hooks)
STEP_BUDGET = 70


def test_views_reshapes_and_allocations_are_not_counted_and_work_is():
    x = torch.rand(4, 6)
    with OperatorCount() as counted:
        y = x.view(6, 4).reshape(3, 8).t()[2:].unsqueeze(0)  # views: no kernel
        torch.empty(3)
        z = (y * 2.0 + 1.0).sum()
    assert dict(counted.counts) == {"mul": 1, "add": 1, "sum": 1}, counted.counts
    assert float(z) > 0


def test_a_splat_gpu_preset_step_dispatches_at_most_its_budget_of_operators(make_config, scene_cache, monkeypatch):
    monkeypatch.setenv("NERF_LIGHTNING_CACHE", str(scene_cache))
    # splat_blender_gpu's model, optimiser and strategy on the built-in scene (a Blender-like object), on the CPU with
    # numba's tiles; steps 1 to 6, before any refinement (as a run's first 500 steps)
    cfg = make_config("experiment=splat_blender_gpu", "data/scene=procedural", "data.scene.size=48",
                      "model.start.random.count=2000", "trainer.max_steps=6", "data.val_every=null", "trainer.accelerator=cpu",
                      "trainer.enable_progress_bar=false", "trainer.enable_model_summary=false", "callbacks=none", "~logger",
                      "+callbacks.operators._target_=nerf_lightning.bench.operators.StepOperatorCounter",
                      "+callbacks.operators.first=1", "+callbacks.operators.last=6")
    counters = []
    original = StepOperatorCounter.__init__

    def keep(self, *args, **kwargs):
        original(self, *args, **kwargs)
        counters.append(self)

    monkeypatch.setattr(StepOperatorCounter, "__init__", keep)
    train(cfg)
    (counter,) = counters
    assert len(counter.steps) == 6
    per_step = counter.per_step
    # the whole step is counted: the optimiser's update and the backward pass are in it
    assert per_step.get("_fused_adam_", 0) >= 6 and per_step.get("sigmoid_backward", 0) >= 1, per_step
    assert counter.total <= STEP_BUDGET, f"{counter.total:.1f} operators a step: {per_step}"
