"""What GPUs and Apple GPUs need, checked on a CPU: no float64 in a training step, bf16 autocast, the device key."""

from __future__ import annotations

import subprocess
import sys

import lightning as L
import pytest
import torch
from torch.utils._python_dispatch import TorchDispatchMode
from torch.utils._pytree import tree_leaves

from hydra.utils import instantiate

from nerf_lightning.devices import resolve_device
from nerf_lightning.splats.draw import FastKernels
from tests.test_experiments import EXPERIMENTS, tiny_data, tiny_overrides  # noqa: F401 (tiny_data is a fixture)

RADIANCE_PRESETS = [name for name in EXPERIMENTS if name != "image"]
# the CPU-sized fast presets: the GPU-sized ones (128^3 occupancy grid, 16 hash levels) train the same code, 50 steps
# of them take two minutes on a CPU
FAST_PRESETS = [name for name in EXPERIMENTS if name.startswith("fast") and not name.endswith("_gpu")]


class NoFloat64(TorchDispatchMode):
    """Fails on any op that takes or makes a float64 tensor: Apple GPUs (MPS) have no float64."""

    def __torch_dispatch__(self, func, types, args=(), kwargs=None):
        kwargs = kwargs or {}
        out = func(*args, **kwargs)
        for value in tree_leaves((args, kwargs, out)):
            if (isinstance(value, torch.Tensor) and value.dtype == torch.float64) or value is torch.float64:
                raise AssertionError(f"{func} uses float64, which Apple GPUs do not have")
        return out


class TrainingStepsWithoutFloat64(L.Callback):
    """Runs every training step (forward, sampler update, backward, optimiser step) under :class:`NoFloat64`."""

    def __init__(self) -> None:
        self.mode: NoFloat64 | None = None
        self.steps = 0

    def on_train_batch_start(self, trainer, pl_module, batch, batch_idx):
        with NoFloat64():  # the rays and colours of the batch, made as on the device
            trainer.datamodule.on_after_batch_transfer({"pixel_index": torch.arange(8)}, 0)
        self.mode = NoFloat64()
        self.mode.__enter__()

    def on_train_batch_end(self, trainer, pl_module, outputs, batch, batch_idx):
        self.mode.__exit__(None, None, None)
        self.mode = None
        self.steps += 1

    def on_exception(self, trainer, pl_module, exception):
        if self.mode is not None:  # leave the mode, whatever failed, so that it does not reach the next tests
            self.mode.__exit__(None, None, None)
            self.mode = None


def fit(cfg, callback: L.Callback) -> L.Trainer:
    """Train ``cfg`` as nerf-train does (seeded alike), with ``callback`` watching."""
    L.seed_everything(cfg.seed, workers=True, verbose=False)
    trainer = instantiate(cfg.trainer, callbacks=[callback], logger=False, enable_checkpointing=False)
    trainer.fit(instantiate(cfg.model), datamodule=instantiate(cfg.data))
    return trainer


class LossHistory(L.Callback):
    def __init__(self) -> None:
        self.losses: list[float] = []

    def on_train_batch_end(self, trainer, pl_module, outputs, batch, batch_idx):
        self.losses.append(float(outputs["loss"]))


def test_the_dispatch_mode_catches_float64():
    with pytest.raises(AssertionError, match="float64"), NoFloat64():
        torch.ones(3, dtype=torch.float32).double()


@pytest.mark.parametrize("experiment", RADIANCE_PRESETS)
def test_a_training_step_of_every_preset_uses_no_float64(experiment, tiny_data, make_config, scene_cache, monkeypatch):
    monkeypatch.setenv("NERF_LIGHTNING_CACHE", str(scene_cache))
    # on CUDA the splats' Triton kernels carry transmittance in float64, which CUDA has; an Apple GPU draws with the
    # pairs rasteriser, so that is the one checked here, wherever the test runs
    monkeypatch.setattr(FastKernels, "triton", lambda self: None)
    watcher = TrainingStepsWithoutFloat64()
    trainer = fit(make_config(*tiny_overrides(experiment, tiny_data), "data.val_every=null", "trainer.max_steps=2"), watcher)
    assert trainer.global_step == 2 and watcher.steps == 2


# in CI: the hash grid (fast), the factorised grid (tensorf) and NDC (llff); the Blender and contracted presets train the
# same fields under -m slow
BF16_IN_CI = ("fast", "fast_blender_tensorf", "fast_llff")


@pytest.mark.parametrize("experiment", [name if name in BF16_IN_CI else pytest.param(name, marks=pytest.mark.slow) for name in FAST_PRESETS])
def test_the_fast_presets_learn_under_bf16_mixed_on_a_cpu(experiment, tiny_data, make_config, scene_cache, monkeypatch):
    monkeypatch.setenv("NERF_LIGHTNING_CACHE", str(scene_cache))
    history = LossHistory()
    # bf16 matrix products are slow on a CPU without bf16 units: steps of 0.05 (about 100 across the box, not 260) keep
    # the run short; the NDC preset keeps its own (its loss falls least)
    coarse = [] if experiment == "fast_llff" else ["model.sampler.step_size=0.05"]
    trainer = fit(make_config(*tiny_overrides(experiment, tiny_data), "trainer.precision=bf16-mixed", "trainer.max_steps=50",
                              "data.val_every=null", "data.batch_size=256", *coarse), history)
    assert trainer.global_step == 50 and len(history.losses) == 50
    losses = torch.tensor(history.losses)
    assert bool(torch.isfinite(losses).all())
    assert losses[-10:].mean() < 0.9 * losses[:10].mean()  # the colour loss falls (by 18 to 84% here in 50 steps)


def test_the_device_key_names_what_it_expects():
    assert resolve_device("cpu") == torch.device("cpu") and resolve_device("CPU") == torch.device("cpu")
    assert resolve_device("auto").type in ("cpu", "cuda", "mps")
    with pytest.raises(ValueError, match=r"device must be auto, cpu, cuda, cuda:<index> or mps, got 'tpu'"):
        resolve_device("tpu")
    if not torch.cuda.is_available():
        with pytest.raises(ValueError, match=r"device=cuda: this machine has no such CUDA device \(it has cpu"):
            resolve_device("cuda")


@pytest.mark.parametrize("command", ["render", "evaluate", "export"])
def test_a_bad_device_stops_the_command_in_one_line(command, tmp_path):
    result = subprocess.run([sys.executable, "-m", f"nerf_lightning.cli.{command}", f"ckpt_path={tmp_path / 'x.ckpt'}", "device=gpu"],
                            cwd=tmp_path, capture_output=True, text=True, timeout=120)
    assert result.returncode == 2 and "Traceback" not in result.stderr
    assert "device must be auto, cpu, cuda, cuda:<index> or mps, got 'gpu'" in result.stderr
