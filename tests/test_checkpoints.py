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
