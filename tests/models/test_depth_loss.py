"""The depth loss (model.depth_loss for a NeRF, model.loss.depth_loss for splats) on a phone-style capture of the
procedural scene (depth maps a quarter the photos' side, 2% noise): both train with it, and nerf-eval scores depth
error against the true depth of the same views."""

import pytest
import torch

from nerf_lightning.config import compose_config
from nerf_lightning.data.formats.depth_capture import write_depth_capture
from nerf_lightning.data.scene import Scene
from nerf_lightning.models.base import depth_for_depth_loss
from nerf_lightning.outputs.evaluation import evaluate_checkpoint
from nerf_lightning.splats.loss import SplatLoss
from nerf_lightning.training import train


@pytest.fixture(scope="module")
def captures(procedural_scene, tmp_path_factory):
    """A phone-style capture of 12 training and 2 held-out views, and the same views with their true depth."""
    splits = {"train": procedural_scene.train.subset(list(range(0, 24, 2))), "val": procedural_scene.splits["val"].subset([0, 1])}
    scene = Scene(splits=splits, near=procedural_scene.near, far=procedural_scene.far, background=procedural_scene.background)
    root = tmp_path_factory.mktemp("depth_captures")
    return (write_depth_capture(scene, root / "phone", shrink=4, noise=0.02),
            write_depth_capture(scene, root / "truth", suffix=".npy"))


def scene_overrides(path) -> list[str]:
    """The capture in the procedural scene's own world (not normalised), so the presets' boxes and bounds hold."""
    return ["data/scene=transforms", f"data.root={path}", "data.scene.downscale=1", "data.scene.normalise=false",
            "data.scene.near=2.0", "data.scene.far=6.0", "data.scene.background=[1.0,1.0,1.0]", "trainer.accelerator=cpu",
            "trainer.enable_progress_bar=false", "trainer.enable_model_summary=false", "data.val_views=1"]


def test_a_nerf_trains_with_the_depth_loss_and_nerf_eval_scores_depth(captures, tmp_path):
    phone, truth = captures
    config = compose_config(["experiment=fast", *scene_overrides(phone), "model.field.encoding.n_levels=4",
                             "model.field.encoding.log2_table_size=12", "model.field.encoding.max_resolution=64",
                             "model.field.encoding.compile_evaluation=false",
                             "model.sampler.grid.resolution=16", "data.batch_size=128", "trainer.max_steps=6",
                             "data.val_every=6", "model.depth_loss=0.1", f"paths.output_dir={tmp_path / 'run'}"])
    metrics = train(config)
    assert 0 < metrics["train/loss_depth"] < 1 and metrics["val/depth_error"] > 0
    result = evaluate_checkpoint(tmp_path / "run" / "checkpoints" / "last.ckpt", tmp_path / "eval", split="val", root=truth, lpips="off")
    assert result["views"] == 2 and 0 < result["mean"]["depth_error"] < 2


def test_splats_train_with_the_depth_loss(captures, tmp_path):
    config = compose_config(["experiment=splat_procedural", *scene_overrides(captures[0]), "model/rasterizer=pairs",
                             "model.start.random.count=500", "trainer.max_steps=6", "data.val_every=6",
                             "model.loss.depth_loss=0.1", f"paths.output_dir={tmp_path / 'run'}"])
    metrics = train(config)
    assert 0 < metrics["train/loss_depth"] < 1 and metrics["val/depth_error"] > 0


def test_the_depth_loss_without_depth_says_what_it_needs():
    with pytest.raises(ValueError, match="model.depth_loss > 0 needs depth in each training batch"):
        depth_for_depth_loss({"rgb": torch.zeros(2, 3)})
    with pytest.raises(ValueError, match="model.loss.depth_loss > 0 needs depth"):
        SplatLoss(depth_loss=0.1).of_depth(torch.zeros(2, 2), None)
    with pytest.raises(ValueError, match="model.loss.depth_loss must be a number >= 0"):
        SplatLoss(depth_loss=-1.0)


def test_the_shipped_models_have_the_depth_loss_off(make_config):
    assert make_config("experiment=fast").model.depth_loss == 0.0
    assert make_config("experiment=splat_procedural").model.loss.depth_loss == 0.0
