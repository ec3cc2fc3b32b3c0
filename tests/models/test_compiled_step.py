"""model.compile: the GPU presets' training step as one graph through torch.compile(fullgraph=True), on the CPU."""

from __future__ import annotations

import functools

import lightning as L
import pytest
import torch._inductor.config as inductor_config
from hydra.utils import instantiate

from nerf_lightning.config import compose_config
from nerf_lightning.models import radiance_field

PRESETS = {  # the presets as they are, on small scenes, their buffers sized for 256 rays (as tests/rendering/test_fixed_shapes.py)
    "nerfacto_360_gpu": ["experiment=nerfacto_360_gpu", "data=turntable", "data.scene.size=32", "data.scene.n_photos=16"],
    "fast_blender_gpu": ["experiment=fast_blender_gpu", "data=procedural", "data.scene.size=32", "model.sampler.grid.resolution=32",
                         "model.sampler.capacity=16384", "model.sampler.march_capacity=65536"],
}


class StepLosses(L.Callback):
    def __init__(self) -> None:
        self.losses: list[float] = []

    def on_train_batch_end(self, trainer, module, outputs, batch, batch_idx) -> None:
        self.losses.append(float(outputs["loss"]))


def fit(preset: str, compile: bool, steps: int = 4) -> tuple[L.LightningModule, list[float]]:
    cfg = compose_config([*PRESETS[preset], "data.batch_size=256", "data.val_every=null", f"model.compile={compile}"])
    L.seed_everything(0, verbose=False)
    datamodule, model = instantiate(cfg.data), instantiate(cfg.model)
    losses = StepLosses()
    trainer = L.Trainer(max_steps=steps, logger=False, enable_checkpointing=False, enable_progress_bar=False,
                        enable_model_summary=False, limit_val_batches=0, callbacks=[losses])
    trainer.fit(model, datamodule=datamodule)
    return model, losses.losses


# inductor builds C++ for the step and its backward: fast_blender_gpu's in about half a minute on two cores,
# nerfacto_360_gpu's (three hash grids) in about a minute and a half, so CI traces that one with aot_eager (the same
# graph, without a graph break: fullgraph=True, and the same backward through AOTAutograd, run by eager kernels)
@pytest.mark.parametrize("preset, backend", [
    ("fast_blender_gpu", "inductor"),
    ("nerfacto_360_gpu", "aot_eager"),
    pytest.param("nerfacto_360_gpu", "inductor", marks=pytest.mark.slow),
])
def test_the_compiled_step_is_one_graph_and_trains_as_the_plain_step(preset, backend, scene_cache, monkeypatch):
    monkeypatch.setenv("NERF_LIGHTNING_CACHE", str(scene_cache))
    monkeypatch.setattr(radiance_field, "CompiledOrEager", functools.partial(radiance_field.CompiledOrEager, backend=backend))
    plain, plain_losses = fit(preset, compile=False)
    with inductor_config.patch(fallback_random=True):  # random numbers drawn as eagerly (inductor's own generator draws others)
        compiled, compiled_losses = fit(preset, compile=True)
    assert plain.compiled_step is None
    # fullgraph=True: a graph break would have failed the compile, and CompiledOrEager would have gone on plainly
    assert compiled.compiled_step.compiled is not None and compiled.compiled_step.failure is None
    assert len(compiled_losses) == len(plain_losses) == 4
    # four steps of Adam from the same weights on the same rays: the same losses to float32's summation order
    assert compiled_losses == pytest.approx(plain_losses, rel=1e-4)
    assert len(set(plain_losses)) == 4  # it trained: each step's loss its own


def test_compiling_a_step_whose_sizes_depend_on_the_data_is_refused_in_one_line():
    cfg = compose_config(["experiment=fast_blender", "model.compile=true"])
    with pytest.raises(Exception, match="model.compile=true needs a training step of fixed shapes"):
        instantiate(cfg.model)
