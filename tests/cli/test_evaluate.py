"""nerf-eval run as a user runs it."""

import json
import os
import subprocess
import sys

import pytest

from nerf_lightning.training import train

QUIET = ["trainer.enable_progress_bar=false", "trainer.enable_model_summary=false"]


def test_eval_on_a_missing_second_capture_is_named(tmp_path, make_config):
    run = tmp_path / "trained"
    train(make_config("experiment=fast", "model.field.encoding.n_levels=2", "model.field.encoding.log2_table_size=10", "model.field.encoding.max_resolution=32",
                      "model.sampler.grid.resolution=8", "data.batch_size=64", "trainer.max_steps=2", "data.val_every=2",
                      "data.val_views=1", *QUIET, run_dir=run))
    result = subprocess.run([sys.executable, "-m", "nerf_lightning.cli.evaluate", f"ckpt_path={run / 'checkpoints' / 'last.ckpt'}",
                             f"root={tmp_path / 'other.json'}", f"output_dir={tmp_path / 'eval'}"],
                            cwd=tmp_path, capture_output=True, text=True, timeout=300)
    assert result.returncode == 2 and "Traceback" not in result.stderr, result.stderr[-3000:]
    lines = [line for line in result.stderr.splitlines() if line.startswith("nerf-eval: error:")]
    assert len(lines) == 1 and str(tmp_path / "other.json") in lines[0] and "not found" in lines[0], result.stderr[-3000:]
    assert not (tmp_path / "eval" / "eval.json").exists()


@pytest.mark.slow  # trains and evaluates twice; tests/outputs/test_lpips.py holds the network in CI
def test_eval_adds_lpips_with_weights_and_says_once_why_it_is_absent_without(tmp_path, make_config):
    from tests.outputs.test_lpips import written_weights

    run = tmp_path / "trained"
    train(make_config("experiment=fast", "model.field.encoding.n_levels=2", "model.field.encoding.log2_table_size=10", "model.field.encoding.max_resolution=32",
                      "model.sampler.grid.resolution=8", "data.batch_size=64", "trainer.max_steps=2", "data.val_steps=[]",
                      *QUIET, run_dir=run))
    ckpt = run / "checkpoints" / "last.ckpt"
    environment = {**os.environ, "TORCH_HOME": str(tmp_path / "empty_torch_home")}  # no AlexNet weights in its hub cache
    command = [sys.executable, "-m", "nerf_lightning.cli.evaluate", f"ckpt_path={ckpt}", "max_views=2", "device=cpu"]
    skipped = subprocess.run([*command, f"output_dir={tmp_path / 'without'}"], cwd=tmp_path, env=environment,
                             capture_output=True, text=True, timeout=300)
    assert skipped.returncode == 0, skipped.stderr[-3000:]
    said = json.loads((tmp_path / "without" / "eval.json").read_text())
    assert "lpips" not in said["mean"] and said["lpips"]["skipped"].startswith("LPIPS skipped: no AlexNet weights")
    assert (skipped.stdout + skipped.stderr).count("LPIPS skipped") == 1

    weights = written_weights(tmp_path / "lpips.pth")
    scored = subprocess.run([*command, f"eval.lpips_weights={weights}", f"output_dir={tmp_path / 'with'}"], cwd=tmp_path,
                            env=environment, capture_output=True, text=True, timeout=300)
    assert scored.returncode == 0, scored.stderr[-3000:]
    said = json.loads((tmp_path / "with" / "eval.json").read_text())
    assert said["lpips"] == {"network": "LPIPS 0.1, AlexNet", "weights": str(weights)}
    assert said["mean"]["lpips"] > 0.0 and all(row["lpips"] > 0.0 for row in said["per_view"])
