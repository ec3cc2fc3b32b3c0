"""The shipped data configs build working ray DataModules from data.root alone."""

import torch
from hydra.utils import instantiate

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
