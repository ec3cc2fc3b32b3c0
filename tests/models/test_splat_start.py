"""The splats' start as objects (model/start, model/start/random), the loss as model.loss, and what became of the keys
of before 0.4: a command line that uses one is answered in one line naming the new key, and a checkpoint that holds
them loads as it trained."""

from __future__ import annotations

import pytest
import torch
from hydra.utils import instantiate
from omegaconf import OmegaConf

from nerf_lightning.config import renamed_key_message
from nerf_lightning.models.splat_start import BoxStart, SparsePointsStart, TriangulatedStart, ViewsStart
from nerf_lightning.splats.loss import SplatLoss


def test_the_presets_choose_their_start_and_the_default_is_the_sparse_points_else_a_box(make_config):
    default = instantiate(make_config("experiment=splat_procedural").model)
    assert type(default.start) is SparsePointsStart and type(default.start.random) is BoxStart
    assert (default.start.random.count, default.start.random.extent, default.start.beside) == (20000, 1.3, 0)
    assert default.loss == SplatLoss(ssim_weight=0.2, mask_loss=0.0, train_background="scene")
    assert default.gaussians.sh_degree_interval == 1000
    forward = instantiate(make_config("experiment=splat_forward_cpu").model)
    assert type(forward.start) is TriangulatedStart and type(forward.start.random) is ViewsStart
    assert (forward.start.random.count, forward.start.random.near, forward.start.random.far, forward.start.random.scale,
            forward.start.beside) == (20000, None, 10.0, 0.4, 10000)
    assert forward.gaussians.sh_degree_interval == 500
    obj = instantiate(make_config("experiment=splat_object_cpu").model)
    assert type(obj.start) is TriangulatedStart and obj.start.random.near == 0.3 and obj.loss.train_background == "random"
    # the random start's choice under a triangulated start, from the command line
    boxed = make_config("experiment=splat_360_cpu", "model/start/random=box", "model.start.random.count=10")
    assert boxed.model.start._target_.endswith("TriangulatedStart") and boxed.model.start.random._target_.endswith("BoxStart")


@pytest.mark.parametrize("old, new", [
    ("model.random_count=5", "use model.start.random.count"),
    ("model.random_start=views", "use model/start/random=box or model/start/random=views"),
    ("model.random_near=0.3", "use model.start.random.near (with model/start/random=views)"),
    ("model.random_extent=3", "use model.start.random.extent (with model/start/random=views: model.start.random.far)"),
    ("model.random_scale=0.2", "use model.start.random.scale"),
    ("model.triangulate=true", "use model/start=triangulated (model/start=points for false)"),
    ("model.random_beside_points=10", "use model.start.beside"),
    ("model.ssim_weight=0.1", "use model.loss.ssim_weight"),
    ("model.sh_degree_interval=400", "use model.gaussians.sh_degree_interval"),
])
def test_a_key_of_before_0_4_is_answered_with_the_key_now(old, new):
    message = renamed_key_message(["experiment=splat_360_cpu", old])
    assert message.startswith(f"'{old.partition('=')[0]}' was moved in nerf-lightning 0.4") and message.endswith(new), message


def test_the_loss_keys_moved_for_the_splats_alone():
    assert renamed_key_message(["experiment=splat_object_cpu", "model.mask_loss=0.5"]).endswith("use model.loss.mask_loss")
    assert renamed_key_message(["model=splat", "model.train_background=random"]).endswith("use model.loss.train_background")
    assert renamed_key_message(["experiment=nerfacto_object_cpu", "model.mask_loss=0.5"]) is None  # a NeRF's key still
    assert renamed_key_message(["experiment=splat_object_cpu", "model.loss.mask_loss=0.5"]) is None


def test_a_checkpoint_written_before_0_4_loads_with_its_start_loss_and_strategy(make_config, tmp_path):
    """Its model config holds the start's, the loss's keys and sh_degree_interval at the top, MCMC at its old path."""
    from nerf_lightning import __version__
    from nerf_lightning.checkpoints import CHECKPOINT_FORMAT, load_model
    from nerf_lightning.splats.mcmc import MCMCStrategy

    cfg = make_config("experiment=splat_forward_cpu", "model/strategy=mcmc", "data.root=unused")
    config = OmegaConf.to_container(cfg, resolve=True)
    model = config["model"]
    for key in ("start", "loss"):
        del model[key]
    del model["gaussians"]["sh_degree_interval"]
    model["strategy"]["_target_"] = "nerf_lightning.splats.strategy.MCMCStrategy"
    model.update(triangulate=True, random_beside_points=7, random_count=300, random_start="views", random_near=None,
                 random_extent=9.0, random_scale=0.4, sh_degree_interval=450, ssim_weight=0.3, mask_loss=0.1,
                 train_background="random")
    trained = instantiate(make_config("experiment=splat_forward_cpu").model)
    path = tmp_path / "old.ckpt"
    torch.save({"state_dict": trained.state_dict(), "global_step": 0,
                "nerf_lightning": {"kind": "splats", "config": config, "format": CHECKPOINT_FORMAT, "version": __version__}}, path)
    loaded, info = load_model(path)
    assert type(loaded.start) is TriangulatedStart and type(loaded.start.random) is ViewsStart
    assert (loaded.start.random.count, loaded.start.random.near, loaded.start.random.far, loaded.start.random.scale,
            loaded.start.beside) == (300, None, 9.0, 0.4, 7)
    assert loaded.loss == SplatLoss(ssim_weight=0.3, mask_loss=0.1, train_background="random")
    assert loaded.gaussians.sh_degree_interval == 450 and isinstance(loaded.strategy, MCMCStrategy)
    assert "random_count" not in info["config"]["model"] and info["config"]["model"]["start"]["beside"] == 7
    # a box start keeps its extent; without the keys a checkpoint never had, the objects' defaults
    boxed = {key: value for key, value in model.items() if key not in ("random_start", "random_near", "random_beside_points", "mask_loss")}
    from nerf_lightning.models.splat_config import config_before_04

    upgraded = config_before_04(boxed)
    assert upgraded["start"]["random"] == {"_target_": "nerf_lightning.models.splat_start.BoxStart", "count": 300, "scale": 0.4,
                                           "extent": 9.0}
    assert "beside" not in upgraded["start"] and "mask_loss" not in upgraded["loss"]
    assert config_before_04(upgraded) == upgraded  # a config of 0.4 passes through


def test_the_start_and_loss_refuse_bad_values_by_their_keys():
    with pytest.raises(ValueError, match="model.start.random.count must be an integer >= 0, got -1"):
        BoxStart(count=-1)
    with pytest.raises(ValueError, match="model.start.random.extent must be > 0"):
        BoxStart(extent=0.0)
    with pytest.raises(ValueError, match="model.loss.ssim_weight must be a number in \\[0, 1\\], got 2"):
        SplatLoss(ssim_weight=2)
    with pytest.raises(ValueError, match="model.loss.mask_loss must be a number >= 0"):
        SplatLoss(mask_loss=-1.0)


def test_nerf_train_answers_a_start_key_of_before_0_4_in_one_line(tmp_path):
    import subprocess
    import sys

    result = subprocess.run([sys.executable, "-m", "nerf_lightning.cli.train", "experiment=splat_360_cpu", "model.triangulate=true"],
                            cwd=tmp_path, capture_output=True, text=True)
    assert result.returncode != 0 and "Traceback" not in result.stderr
    assert "'model.triangulate' was moved in nerf-lightning 0.4" in result.stderr and "use model/start=triangulated" in result.stderr
