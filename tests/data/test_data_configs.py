"""The shipped data configs build working ray DataModules from data.root alone; the format presets share one ray block."""

import torch
from hydra.utils import instantiate
from omegaconf import OmegaConf

from nerf_lightning.config import compose_config
from nerf_lightning.data.formats import load_blender, save_npz
from tests.conftest import run_cli


def build(*overrides):
    data = instantiate(compose_config([*overrides, "paths.output_dir=/tmp/unused"]).data)
    data.setup()
    return data


def test_make_scene_then_data_blender(tmp_path, procedural_scene):
    result = run_cli("make_scene", str(tmp_path / "scene"), "--views", "20", "--size", "32", cwd=tmp_path)
    assert "20 views, 32x32" in result.stdout
    small = load_blender(tmp_path / "scene")
    assert (len(small.train), len(small.splits["val"]), len(small.splits["test"])) == (16, 2, 2)
    assert small.train.images.shape == (16, 32, 32, 3) and small.train.depth.shape == (16, 32, 32)

    data = build("data=blender", f"data.root={tmp_path / 'scene'}", "data.batch_size=64", "data.val_views=2")
    assert data.scene.train.height == 32 and len(data.validation_views()) == 2
    assert data.on_after_batch_transfer(next(iter(data.train_dataloader())), 0)["rays_o"].shape == (64, 3)


def test_data_npz(tmp_path, procedural_scene):
    path = save_npz(procedural_scene, tmp_path / "course.npz")
    data = build("data=npz", f"data.root={path}", "data.batch_size=128")
    torch.testing.assert_close(data.scene.train.c2w, procedural_scene.train.c2w)
    # the npz's c2ws_test is its render path
    assert len(data.render_views()) == len(procedural_scene.splits["test"])


def test_data_procedural_is_the_default_radiance_scene(scene_cache, monkeypatch):
    monkeypatch.setenv("NERF_LIGHTNING_CACHE", str(scene_cache))
    data = build("data=procedural", "data.batch_size=32")
    assert len(data.scene.train) == 80 and data.scene.train.depth is not None
    assert len(data.render_views()) == 60  # an orbit


def test_the_format_presets_are_the_shared_ray_block_with_their_own_values():
    shared = {"_target_": "nerf_lightning.data.RayDataModule", "ndc": False, "contract": False, "batch_size": 10000, "masks": None, "object_box": None, "object_share": None, "val_views": 3,
              "val_split": "val", "render_path": "test", "render_frames": 60, "val_steps": [], "val_every": 500, "seed": "${seed}"}
    own = {"blender": {"root": "x"}, "npz": {"root": "x"},
           "llff": {"root": "x", "batch_size": 4096, "render_path": "spiral", "render_frames": 120},
           "transforms": {"root": "x", "batch_size": 4096, "val_views": 2, "render_path": "spiral", "render_frames": 120},
           "procedural": {"render_path": "orbit"}}
    for name, values in own.items():
        root = ["data.root=x"] if "root" in values else []
        data = OmegaConf.to_container(compose_config([f"data={name}", *root, "paths.output_dir=/tmp/unused"]).data)
        assert data.pop("scene")["_target_"] == f"nerf_lightning.data.formats.load_{name}"
        assert data == {**shared, **values}, name
    # any format's scene under another datamodule
    views = compose_config(["data=views", "data/scene=llff", "data.root=x", "paths.output_dir=/tmp/unused"]).data
    assert views._target_ == "nerf_lightning.data.ViewDataModule" and views.scene.downscale == 8 and views.patch_size is None
