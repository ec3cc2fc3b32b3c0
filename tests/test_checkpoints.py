import pytest
import torch

from nerf_lightning.checkpoints import load_model, run_dir_of


def test_missing_checkpoint_is_named(tmp_path):
    with pytest.raises(FileNotFoundError, match="checkpoint not found: .*nope.ckpt"):
        load_model(tmp_path / "nope.ckpt")


def test_a_file_that_is_not_a_nerf_train_checkpoint_is_refused(tmp_path):
    torch.save({"state_dict": {}}, tmp_path / "other.ckpt")
    with pytest.raises(ValueError, match="other.ckpt is not a nerf-train checkpoint"):
        load_model(tmp_path / "other.ckpt")
    (tmp_path / "text.ckpt").write_text("hello")
    with pytest.raises(ValueError, match="could not read checkpoint .*text.ckpt"):
        load_model(tmp_path / "text.ckpt")


def test_run_dir_of():
    assert run_dir_of("/a/run/checkpoints/last.ckpt").as_posix() == "/a/run"
    assert run_dir_of("/a/elsewhere/model.ckpt").as_posix() == "/a/elsewhere"


def test_a_checkpoint_of_another_model_kind_is_refused_by_name(make_config, tmp_path):
    from nerf_lightning.train import train

    train(make_config("experiment=image", "data.downscale=8", "data.batch_size=64", "trainer.max_steps=2", "data.val_steps=[]",
                      "trainer.enable_progress_bar=false", run_dir=tmp_path / "image"))
    ckpt = tmp_path / "image" / "checkpoints" / "last.ckpt"
    model, info = load_model(ckpt, kind="image_field")
    assert info["kind"] == "image_field" and info["global_step"] == 2
    with pytest.raises(ValueError, match="holds a model of kind 'image_field'; nerf-eval works with radiance_field checkpoints"):
        load_model(ckpt, kind="radiance_field", command="nerf-eval")
