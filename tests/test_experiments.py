"""Every shipped experiment preset composes, instantiates, and trains two steps on tiny data in its own format."""

from __future__ import annotations

from pathlib import Path

import pytest
import torch

import nerf_lightning.conf
from nerf_lightning.config import compose_config
from nerf_lightning.data.formats.npz import save_npz
from nerf_lightning.data.formats.procedural import make_procedural_scene
from nerf_lightning.io import write_png
from nerf_lightning.training import train
from tests.data.test_llff import write_llff
from tests.data.test_transforms import write_transforms

EXPERIMENTS = sorted(path.stem for path in (Path(nerf_lightning.conf.__file__).parent / "experiment").glob("*.yaml"))

# Small enough for two steps of any preset in seconds: a few views of 16x16, few rays, small fields
TINY = ["trainer.max_steps=2", "trainer.enable_progress_bar=false", "logger={}", "callbacks={}", "data.batch_size=64",
        "++trainer.limit_val_batches=1", "++trainer.num_sanity_val_steps=0"]


@pytest.fixture(scope="module")
def tiny_data(tmp_path_factory, procedural_scene) -> dict[str, Path]:
    """The procedural scene at 16x16 as a Blender folder, a course .npz, LLFF and transforms.json captures, one PNG."""
    root = tmp_path_factory.mktemp("tiny")
    blender = make_procedural_scene(root / "blender", n_views=20, size=16)
    from nerf_lightning.data.formats import load_blender

    scene = load_blender(blender)
    llff = write_llff(scene.train.subset(list(range(8))), root / "llff", downscale=2)
    transforms = write_transforms(scene.train.subset(list(range(8))), root / "transforms")
    write_png(root / "image.png", scene.train.images[0])
    return {"blender": blender, "npz": save_npz(scene, root / "scene.npz"), "llff": llff, "transforms": transforms,
            "image": root / "image.png"}


def tiny_overrides(experiment: str, tiny_data: dict[str, Path]) -> list[str]:
    """``experiment`` on the tiny data in its format (see :func:`tiny_data`), a few rays a step, one small validation."""
    cfg = compose_config([f"experiment={experiment}", "paths.output_dir=/tmp/unused"])
    scene_target = cfg.data.scene._target_ if "scene" in cfg.data else ""
    overrides = [f"experiment={experiment}", *TINY]
    if cfg.data._target_.endswith("ViewDataModule"):  # a view a step (no batch size); a few Gaussians
        overrides = [o for o in overrides if not o.startswith("data.batch_size")] + ["model.start.random.count=500"]
        if cfg.data.patch_size is not None:  # patches of the tiny views
            overrides.append("data.patch_size=8")
    if cfg.data._target_.endswith("PixelDataModule"):
        return overrides + [f"data.path={tiny_data['image']}", "data.val_steps=[1,2]"]
    overrides += [*(["data.scene.max_views=4"] if "max_views" in cfg.data.scene else []), "data.val_every=2", "data.val_views=1",
                  "data.render_frames=2"]
    if cfg.data.get("masks") in ("background", "exclude") and cfg.data._target_.endswith("ViewDataModule"):
        # a masked object's splats need masks: the built-in turntable's scene, 12 photos of 32x32, a view a step
        overrides = [o for o in overrides if not o.startswith("data.scene.max_views")]
        return overrides + ["data/scene=turntable", "data.scene.n_photos=12", "data.scene.size=32", "data.scene.holdout_every=4"]
    if cfg.data.get("object_box"):  # an object's box needs its masks: the built-in turntable, 12 photos of 32x32
        overrides = [o for o in overrides if not o.startswith("data.scene.max_views")]
        return overrides + ["data/scene=turntable", "data.scene.n_photos=12", "data.scene.size=32", "data.scene.holdout_every=4",
                            *(["model.sampler.bake_resolution=16"] if (cfg.model.get("sampler") or {}).get("bake_resolution") else [])]
    for fmt in ("blender", "npz", "llff", "transforms"):
        if scene_target.endswith(f"load_{fmt}"):
            overrides.append(f"data.root={tiny_data[fmt]}")
    if scene_target.endswith(("load_llff", "load_transforms")):
        overrides += ["data.scene.downscale=2", "data.scene.max_views=8"]
    if scene_target.endswith("load_blender"):
        overrides.append("data.scene.downscale=1")
    if scene_target.endswith("load_procedural"):
        overrides.append("data.scene.size=16")
    sampler = cfg.model.get("sampler") or {}
    if "grid" in sampler:  # an occupancy grid of 32^3: the GPU presets' 128^3 takes 20 s a refresh on a CPU
        overrides.append("model.sampler.grid.resolution=32")
    if cfg.data.get("ndc"):  # 8 views from around the procedural scene, not a forward-facing capture: its rays reach |x| = 34 in NDC
        overrides.append("model.field.aabb=[-40.0,-40.0,-1.0,40.0,40.0,1.0]")
    if sampler.get("bake_resolution"):  # proposal networks baked for validation at 16^3, not 128^3
        overrides.append("model.sampler.bake_resolution=16")
    if sampler.get("samples_per_step"):  # a fixed-shape table of a few thousand samples, not Instant-NGP's 2^18 (half a minute a CPU step)
        overrides += ["model.sampler.samples_per_step=8192", "model.sampler.density_pass_samples=32768"]
    if cfg.model.get("compile"):  # the step run plainly: tests/models/test_compiled_step.py compiles it (a minute on a CPU)
        overrides.append("model.compile=false")
    return overrides


@pytest.mark.parametrize("experiment", EXPERIMENTS)
def test_every_experiment_instantiates_and_trains_two_steps(experiment, tiny_data, make_config, scene_cache, monkeypatch):
    monkeypatch.setenv("NERF_LIGHTNING_CACHE", str(scene_cache))
    metrics = train(make_config(*tiny_overrides(experiment, tiny_data)))
    assert metrics["step"] == 2
    losses = [value for key, value in metrics.items() if key.startswith("train/loss")]
    assert losses and all(torch.isfinite(torch.tensor(losses)))
