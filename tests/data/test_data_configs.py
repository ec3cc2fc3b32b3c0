"""The shipped data configs build working ray DataModules from data.root alone: data= the DataModule, data/scene= the
format, which sets what it needs of either DataModule; the old data=<format> choices answered with what to write now."""

import subprocess
import sys

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

    data = build("data=rays", "data/scene=blender", f"data.root={tmp_path / 'scene'}", "data.batch_size=64", "data.val_views=2")
    assert data.scene.train.height == 32 and len(data.validation_views()) == 2
    assert data.on_after_batch_transfer(next(iter(data.train_dataloader())), 0)["rays_o"].shape == (64, 3)


def test_data_npz(tmp_path, procedural_scene):
    path = save_npz(procedural_scene, tmp_path / "course.npz")
    data = build("data=rays", "data/scene=npz", f"data.root={path}", "data.batch_size=128")
    torch.testing.assert_close(data.scene.train.c2w, procedural_scene.train.c2w)
    # the npz's c2ws_test is its render path
    assert len(data.render_views()) == len(procedural_scene.splits["test"])


def test_data_procedural_is_the_default_radiance_scene(scene_cache, monkeypatch):
    monkeypatch.setenv("NERF_LIGHTNING_CACHE", str(scene_cache))
    data = build("data=rays", "data/scene=procedural", "data.batch_size=32")
    assert len(data.scene.train) == 80 and data.scene.train.depth is not None
    assert len(data.render_views()) == 60  # an orbit


def test_each_format_is_the_shared_ray_block_with_its_own_values():
    shared = {"_target_": "nerf_lightning.data.RayDataModule", "ndc": False, "contract": False, "batch_size": 10000, "masks": None, "object_box": None, "object_share": None, "val_views": 3,
              "val_split": "val", "render_path": "test", "render_frames": 60, "val_steps": [], "val_every": 500, "seed": "${seed}"}
    own = {"blender": {"root": "x"}, "npz": {"root": "x"},
           "llff": {"root": "x", "render_path": "spiral", "render_frames": 120},
           "transforms": {"root": "x", "val_views": 2, "render_path": "spiral", "render_frames": 120},
           "procedural": {"render_path": "orbit"}, "turntable": {"masks": "background", "val_views": 2, "render_path": "orbit"}}
    for name, values in own.items():
        root = ["data.root=x"] if "root" in values else []
        data = OmegaConf.to_container(compose_config(["data=rays", f"data/scene={name}", *root, "paths.output_dir=/tmp/unused"]).data)
        assert data.pop("scene")["_target_"] == f"nerf_lightning.data.formats.load_{name}"
        assert data == {**shared, **values}, name
    # any format's scene under another datamodule
    views = compose_config(["data=views", "data/scene=llff", "data.root=x", "paths.output_dir=/tmp/unused"]).data
    assert views._target_ == "nerf_lightning.data.ViewDataModule" and views.scene.downscale == 8 and views.patch_size is None
    assert views.render_path == "spiral"  # the format's own values, as under data=rays
    # the scene's folder is asked for where the format needs one, and absent where it needs none
    assert OmegaConf.is_missing(compose_config(["data=views", "data/scene=blender", "paths.output_dir=/tmp/unused"]).data, "root")
    assert "root" not in compose_config(["data=views", "data/scene=procedural", "paths.output_dir=/tmp/unused"]).data


def test_the_old_format_choices_are_answered_with_what_to_write_now(tmp_path):
    """data=blender and the like chose a format's ray DataModule before 0.4; data=image the pixels'."""
    from nerf_lightning.config import renamed_key_message

    assert "use data=rays data/scene=blender (data=views data/scene=blender for model=splat)" in renamed_key_message(
        ["experiment=fast", "data=blender", "data.root=lego"])
    assert renamed_key_message(["data=image"]).endswith("use data=pixels")
    assert renamed_key_message(["data=rays", "data/scene=turntable", "data.scene.size=32"]) is None
    result = subprocess.run([sys.executable, "-m", "nerf_lightning.cli.viz_cameras", "data=turntable"], cwd=tmp_path,
                            capture_output=True, text=True)
    assert result.returncode == 2 and "use data=rays data/scene=turntable" in result.stderr
