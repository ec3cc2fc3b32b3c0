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
    from nerf_lightning.training import train

    train(make_config("experiment=image", "data.downscale=8", "data.batch_size=64", "trainer.max_steps=2", "data.val_steps=[]",
                      "trainer.enable_progress_bar=false", run_dir=tmp_path / "image"))
    ckpt = tmp_path / "image" / "checkpoints" / "last.ckpt"
    model, info = load_model(ckpt, kind="image_field")
    assert info["kind"] == "image_field" and info["global_step"] == 2
    with pytest.raises(ValueError, match="holds a model of kind 'image_field'; nerf-eval works with radiance_field checkpoints"):
        load_model(ckpt, kind="radiance_field", command="nerf-eval")


def test_a_radiance_field_checkpoint_of_0_1_is_refused_in_one_line_naming_its_version(tmp_path):
    """0.1's layout: weights at model.occupancy_grid / model.fine_field, bounds as module attributes, no format key."""
    import subprocess
    import sys

    old = {"state_dict": {"field.encoding.table": torch.zeros(4, 2), "occupancy_grid.binary": torch.ones(2, 2, 2, dtype=torch.bool)},
           "global_step": 100, "nerf_lightning": {"kind": "radiance_field", "config": {"model": {}}}}
    torch.save(old, tmp_path / "old.ckpt")
    with pytest.raises(ValueError, match=r"old.ckpt was written by nerf-lightning 0.1 \(checkpoint format 1\).*git checkout 5bab3ec"):
        load_model(tmp_path / "old.ckpt")
    result = subprocess.run([sys.executable, "-m", "nerf_lightning.cli.render", f"ckpt_path={tmp_path / 'old.ckpt'}"],
                            cwd=tmp_path, capture_output=True, text=True, timeout=120)
    assert result.returncode != 0 and "Traceback" not in result.stderr
    assert "written by nerf-lightning 0.1" in result.stderr and len(result.stderr.strip().splitlines()) == 1


@pytest.mark.parametrize("preset", ["fast", "nerfacto_forward_cpu", "nerf_course"])
def test_an_optimiser_state_saved_before_adam_was_fused_resumes_in_the_fused_one(preset):
    """The radiance-field presets' Adam is fused (model.optimizer.fused=true); a checkpoint written by the loop Adam of
    before (its ``step`` a plain CPU tensor) must resume in it and go on counting from its step."""
    from hydra.utils import instantiate

    from nerf_lightning.config import compose_config

    make = instantiate(compose_config([f"experiment={preset}", "paths.output_dir=/tmp/x"]).model.optimizer)
    torch.manual_seed(0)
    params = [torch.nn.Parameter(torch.randn(5, 2)), torch.nn.Parameter(torch.randn(3))]
    fused = make(params=params)
    assert fused.defaults["fused"] is True
    before = torch.optim.Adam([torch.nn.Parameter(p.detach().clone()) for p in params], lr=fused.defaults["lr"])
    for p in before.param_groups[0]["params"]:
        p.grad = torch.ones_like(p)
    before.step(), before.step()
    fused.load_state_dict(before.state_dict())
    for p in params:
        p.grad = torch.ones_like(p)
    fused.step()
    assert all(float(fused.state[p]["step"]) == 3.0 for p in params)
    assert all(torch.isfinite(p).all() for p in params)
