"""model.compile: the GPU presets' training step as one graph through torch.compile(fullgraph=True), on the CPU."""

from __future__ import annotations

import functools
import warnings

import lightning as L
import pytest
import torch
import torch._inductor.config as inductor_config
from hydra.utils import instantiate
from lightning.pytorch.callbacks import ModelCheckpoint
from torch._dynamo.eval_frame import _debug_get_cache_entry_list

from nerf_lightning import compiling
from nerf_lightning.models.ray_budget import RayBudget
from nerf_lightning.config import compose_config
from nerf_lightning.models import radiance_field

PRESETS = {  # the presets as they are, on small scenes, their buffers sized for 256 rays (as tests/rendering/test_fixed_shapes.py)
    "nerfacto_360_gpu": ["experiment=nerfacto_360_gpu", "data/scene=turntable", "data.scene.size=32", "data.scene.n_photos=16"],
    "fast_blender_gpu": ["experiment=fast_blender_gpu", "data/scene=procedural", "data.scene.size=32", "model.sampler.grid.resolution=32",
                         "model.sampler.samples_per_step=16384", "model.sampler.density_pass_samples=65536"],
}


class StepLosses(L.Callback):
    def __init__(self) -> None:
        self.losses: list[float] = []

    def on_train_batch_end(self, trainer, module, outputs, batch, batch_idx) -> None:
        self.losses.append(float(outputs["loss"]))


class StepRays(L.Callback):
    def __init__(self) -> None:
        self.rays: list[int] = []
        self.fit: list[float] = []

    def on_train_batch_end(self, trainer, module, outputs, batch, batch_idx) -> None:
        self.rays.append(batch["rays_o"].shape[0])
        self.fit.append(float(module.rays_that_fit))


def fit(preset: str, compile: bool, steps: int = 4, callbacks=(), overrides=()) -> tuple[L.LightningModule, list[float]]:
    """``steps`` steps of ``preset`` from the same seed, with ``callbacks`` (the preset's own are left out)."""
    cfg = compose_config([*PRESETS[preset], "data.batch_size=256", "data.val_every=null", f"model.compile={compile}", *overrides])
    L.seed_everything(0, verbose=False)
    datamodule, model = instantiate(cfg.data), instantiate(cfg.model)
    losses = StepLosses()
    trainer = L.Trainer(max_steps=steps, logger=False, enable_checkpointing=False, enable_progress_bar=False,
                        enable_model_summary=False, limit_val_batches=0, callbacks=[losses, *callbacks])
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
    # ten steps: past dynamo's limit of 8 graphs a function, so that a graph a step (a step count read as a constant)
    # would fail the compile
    plain, plain_losses = fit(preset, compile=False, steps=10)
    torch._dynamo.reset()
    with inductor_config.patch(fallback_random=True):  # random numbers drawn as eagerly (inductor's own generator draws others)
        compiled, compiled_losses = fit(preset, compile=True, steps=10)
    assert plain.compiled_step is None
    # fullgraph=True: a graph break would have failed the compile, and CompiledOrEager would have gone on plainly
    assert compiled.compiled_step.compiled is not None and compiled.compiled_step.failure is None
    assert len(_debug_get_cache_entry_list(radiance_field.RadianceFieldModule.step_losses.__code__)) == 1  # one graph for all steps
    assert len(compiled_losses) == len(plain_losses) == 10
    # ten steps of Adam from the same weights on the same rays: the same losses to float32's summation order
    assert compiled_losses == pytest.approx(plain_losses, rel=1e-4)
    assert len(set(plain_losses)) == 10  # it trained: each step's loss its own


def test_compiling_a_step_whose_sizes_depend_on_the_data_is_refused_in_one_line():
    cfg = compose_config(["experiment=fast_blender", "model.compile=true"])
    with pytest.raises(Exception, match="model.compile=true needs a training step of fixed shapes"):
        instantiate(cfg.model)


def test_the_rays_a_step_follow_the_sample_budget_read_a_step_late_and_compile_once(scene_cache, monkeypatch):
    monkeypatch.setenv("NERF_LIGHTNING_CACHE", str(scene_cache))
    budget, rays = RayBudget(fill=0.9, min_rays=64, max_rays=4096, multiple=64), StepRays()
    plain, plain_losses = fit("fast_blender_gpu", compile=False, steps=12, callbacks=[budget, rays])
    # 256 rays want far more than the 16384 samples a step (the grid starts full): fewer rays, once the count is back
    assert rays.rays[0] == 256 and rays.rays[-1] < 256
    for step in range(1, 12):  # each step's rays sized from what an earlier step's wanted, never its own
        if rays.rays[step] != rays.rays[step - 1]:
            assert any(rays.rays[step] == min(max(int(0.9 * fit) // 64 * 64, 64), 4096) for fit in rays.fit[:step - 1]), step
    # compiled: the same losses, and one graph for every ray count (the ray count a symbol, not a constant)
    budget, rays_compiled = RayBudget(fill=0.9, min_rays=64, max_rays=4096, multiple=64), StepRays()
    torch._dynamo.reset()
    with inductor_config.patch(fallback_random=True):
        compiled, compiled_losses = fit("fast_blender_gpu", compile=True, steps=12, callbacks=[budget, rays_compiled])
    assert compiled.compiled_step.failure is None
    assert rays_compiled.rays == rays.rays and len(set(rays.rays)) >= 2
    assert compiled_losses == pytest.approx(plain_losses, rel=1e-4)
    assert len(_debug_get_cache_entry_list(radiance_field.RadianceFieldModule.step_losses.__code__)) == 1


def test_a_ray_budget_needs_a_sampler_of_a_fixed_number_of_samples_a_step(scene_cache, monkeypatch):
    monkeypatch.setenv("NERF_LIGHTNING_CACHE", str(scene_cache))
    with pytest.raises(ValueError, match="callbacks.ray_budget sizes the rays a step to fill the sampler's samples a step, and "
                                         "OccupancyGridSampler .* use model/sampler=fixed_shape_grid"):
        cfg = compose_config(["experiment=fast", "data.scene.size=32", "data.val_every=null"])
        trainer = L.Trainer(max_steps=1, logger=False, enable_checkpointing=False, enable_progress_bar=False, callbacks=[RayBudget()])
        trainer.fit(instantiate(cfg.model), datamodule=instantiate(cfg.data))


def test_a_resumed_run_goes_on_with_the_ray_count_it_had(scene_cache, monkeypatch, tmp_path):
    monkeypatch.setenv("NERF_LIGHTNING_CACHE", str(scene_cache))
    cfg = compose_config([*PRESETS["fast_blender_gpu"], "data.batch_size=256", "data.val_every=null", "model.compile=false"])

    def run(steps: int, ckpt_path=None, min_rays: int = 64, max_rays: int = 4096) -> tuple[RayBudget, StepRays]:
        budget, rays = RayBudget(fill=0.9, min_rays=min_rays, max_rays=max_rays, multiple=64), StepRays()
        checkpoint = ModelCheckpoint(dirpath=tmp_path / str(steps), filename="step", save_top_k=1, every_n_train_steps=steps)
        trainer = L.Trainer(max_steps=steps, logger=False, enable_progress_bar=False, enable_model_summary=False, limit_val_batches=0,
                            callbacks=[budget, rays, checkpoint])
        trainer.fit(instantiate(cfg.model), datamodule=instantiate(cfg.data), ckpt_path=ckpt_path)
        return budget, rays

    first, _ = run(6)
    assert first.rays is not None and first.rays != 256
    _, resumed = run(9, ckpt_path=tmp_path / "6" / "step.ckpt")
    assert resumed.rays[0] == first.rays  # the first step after resuming, not data.batch_size's 256
    # resumed with other bounds (a lower max_rays after running out of memory, say): the saved count is held to them
    # from the first step
    bound = 128 if first.rays != 128 else 192
    _, bounded = run(8, ckpt_path=tmp_path / "6" / "step.ckpt", min_rays=bound, max_rays=bound)
    assert bounded.rays[0] == bound


def test_a_float16_table_needs_loss_scaling(scene_cache, monkeypatch):
    monkeypatch.setenv("NERF_LIGHTNING_CACHE", str(scene_cache))
    with pytest.raises(ValueError, match="table_precision=float16 needs trainer.precision=16-mixed"):
        fit("fast_blender_gpu", compile=False, steps=1, overrides=["model.field.encoding.table_precision=float16"])


def test_where_compiling_fails_the_step_runs_plainly_after_one_warning(scene_cache, monkeypatch):
    monkeypatch.setenv("NERF_LIGHTNING_CACHE", str(scene_cache))

    def no_compiler(function, **options):
        def compiled(*args):
            raise RuntimeError("InvalidCxxCompiler: No working C++ compiler found")
        return compiled

    monkeypatch.setattr(compiling.torch, "compile", no_compiler)
    plain_only = ["model.field.encoding.compile_evaluation=false"]  # the grid refreshes' encoding: not this process's compiled one
    plain, plain_losses = fit("fast_blender_gpu", compile=False, steps=3, overrides=plain_only)
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        compiled, compiled_losses = fit("fast_blender_gpu", compile=True, steps=3, overrides=plain_only)
    failed = [w for w in caught if "torch.compile failed for the training step" in str(w.message)]
    assert len(failed) == 1 and "No working C++ compiler" in str(failed[0].message)
    assert compiled.compiled_step.failure is not None
    assert compiled_losses == pytest.approx(plain_losses, rel=1e-6)
