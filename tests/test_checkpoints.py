import os
import pickle
import re
import shlex

import pytest
import torch

from nerf_lightning.checkpoints import AtomicCheckpointIO, checkpoint_globals, load_model, read_checkpoint
from nerf_lightning.config import run_dir_of

TINY_IMAGE_RUN = ["experiment=image", "data.downscale=8", "data.batch_size=64", "trainer.max_steps=2", "data.val_steps=[]",
                  "trainer.enable_progress_bar=false"]


def test_missing_checkpoint_is_named(tmp_path):
    with pytest.raises(FileNotFoundError, match="checkpoint not found: .*nope.ckpt"):
        load_model(tmp_path / "nope.ckpt")


def test_a_file_that_is_not_a_nerf_train_checkpoint_is_refused(tmp_path):
    torch.save({"state_dict": {}}, tmp_path / "other.ckpt")
    with pytest.raises(ValueError, match="other.ckpt is not a nerf-train checkpoint"):
        load_model(tmp_path / "other.ckpt")
    # a file that is no checkpoint at all is said to be one, with what it holds, not as torch's loader complains
    (tmp_path / "text.ckpt").write_text("hello\nworld")
    with pytest.raises(ValueError, match=r"text.ckpt is not a checkpoint: nerf-train writes its checkpoints as torch.save archives .* "
                                         r"and this file is text \('hello' ...\)"):
        load_model(tmp_path / "text.ckpt")
    (tmp_path / "empty.ckpt").write_bytes(b"")
    with pytest.raises(ValueError, match="empty.ckpt is not a checkpoint: .* this file is empty"):
        load_model(tmp_path / "empty.ckpt")
    (tmp_path / "image.ckpt").write_bytes(b"\x89PNG\r\n\x1a\n\xff\xfe")
    with pytest.raises(ValueError, match="image.ckpt is not a checkpoint: .* this file is 10 bytes of something else"):
        load_model(tmp_path / "image.ckpt")


def test_run_dir_of():
    assert run_dir_of("/a/run/checkpoints/last.ckpt").as_posix() == "/a/run"
    assert run_dir_of("/a/elsewhere/model.ckpt").as_posix() == "/a/elsewhere"


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


@pytest.fixture(scope="module")
def trained_checkpoint(tmp_path_factory):
    """last.ckpt of a two-step nerf-train run of experiment=image, as this version writes it."""
    from nerf_lightning.config import compose_config
    from nerf_lightning.training import train

    run = tmp_path_factory.mktemp("trained")
    train(compose_config([*TINY_IMAGE_RUN, f"paths.output_dir={run}"]))
    return run / "checkpoints" / "last.ckpt"


class ShellCommand:
    """Unpickled, runs ``command`` in a shell: what a shared checkpoint can carry."""

    def __init__(self, command: str) -> None:
        self.command = command

    def __reduce__(self):
        return os.system, (self.command,)


class Allowed:
    """A plain class a checkpoint could hold, for the allow-list's own test."""

    def __init__(self, value: int) -> None:
        self.value = value


def with_entry(trained_checkpoint, path, value):
    """A copy of the real checkpoint ``trained_checkpoint`` at ``path``, with ``value`` added to its dict."""
    checkpoint = torch.load(trained_checkpoint, weights_only=True)
    checkpoint["shared_extra"] = value
    torch.save(checkpoint, path)
    return path


def test_a_checkpoint_that_would_run_code_is_refused_before_it_runs_and_loads_only_with_trust(trained_checkpoint, tmp_path):
    marker = tmp_path / "marker"
    shared = with_entry(trained_checkpoint, tmp_path / "shared.ckpt", ShellCommand(f"touch {shlex.quote(str(marker))}"))
    needed = f"{os.system.__module__}.system"  # posix.system here, nt.system on Windows
    message = rf"^{re.escape(str(shared))} needs `{re.escape(needed)}`, which nerf-lightning checkpoints never hold; if you trust whoever made the file, pass trust_checkpoint=true$"
    with pytest.raises(ValueError, match=message):
        read_checkpoint(shared)
    with pytest.raises(ValueError, match=message):
        load_model(shared)
    assert not marker.exists()

    # trust_checkpoint=true: the file is read whole, and what it carries runs
    checkpoint = read_checkpoint(shared, trust=True)
    assert marker.exists() and checkpoint["shared_extra"] == 0
    marker.unlink()
    model, info = load_model(shared, trust=True)
    assert marker.exists() and info["global_step"] == 2


def test_a_checkpoint_nerf_train_wrote_loads_with_the_default(trained_checkpoint):
    checkpoint = read_checkpoint(trained_checkpoint)
    assert checkpoint["nerf_lightning"]["kind"] == "image_field" and checkpoint["global_step"] == 2
    assert checkpoint["optimizer_states"] and checkpoint["loops"] and checkpoint["callbacks"]
    model, info = load_model(trained_checkpoint)
    loaded = torch.load(trained_checkpoint, weights_only=False)["state_dict"]
    assert all(torch.equal(value, loaded[name]) for name, value in model.state_dict().items())


def test_the_allow_list_is_taken_only_while_a_checkpoint_loads(trained_checkpoint, tmp_path, monkeypatch):
    import nerf_lightning.checkpoints as checkpoints

    shared = with_entry(trained_checkpoint, tmp_path / "allowed.ckpt", Allowed(3))
    with pytest.raises(ValueError, match=r"allowed.ckpt needs `tests.test_checkpoints.Allowed`"):
        read_checkpoint(shared)
    monkeypatch.setattr(checkpoints, "CHECKPOINT_GLOBALS", (Allowed,))
    assert read_checkpoint(shared)["shared_extra"].value == 3
    assert Allowed not in torch.serialization.get_safe_globals()  # the process-wide list is left as it was
    with pytest.raises(pickle.UnpicklingError):
        torch.load(shared, weights_only=True)


def test_lightnings_resume_reader_refuses_the_payload_when_told_weights_only(trained_checkpoint, tmp_path, monkeypatch):
    """trainer.fit(ckpt_path=...) reads the file again, with AtomicCheckpointIO.load_checkpoint(weights_only=...). Its
    default, None, is torch's (True since torch 2.6) unless the environment says TORCH_FORCE_NO_WEIGHTS_ONLY_LOAD, so
    training passes weights_only=not trust_checkpoint: explicit, it holds whatever the environment says."""
    marker = tmp_path / "marker"
    shared = with_entry(trained_checkpoint, tmp_path / "shared.ckpt", ShellCommand(f"touch {shlex.quote(str(marker))}"))
    monkeypatch.setenv("TORCH_FORCE_NO_WEIGHTS_ONLY_LOAD", "1")
    reader = AtomicCheckpointIO()
    with checkpoint_globals():
        assert reader.load_checkpoint(trained_checkpoint, weights_only=True)["global_step"] == 2
        with pytest.raises(pickle.UnpicklingError):
            reader.load_checkpoint(shared, weights_only=True)
        assert not marker.exists()
        with pytest.warns(UserWarning, match="TORCH_FORCE_NO_WEIGHTS_ONLY_LOAD"):
            reader.load_checkpoint(shared, weights_only=None)
    assert marker.exists()
