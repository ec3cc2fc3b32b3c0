"""nerf-eval run as a user runs it."""

import json
import logging
import subprocess
import sys

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


def test_eval_adds_lpips_with_weights_and_says_once_why_it_is_absent_without(tmp_path, make_config, monkeypatch, caplog):
    """What nerf-eval calls (evaluate_checkpoint), in this process: without AlexNet weights eval.json says why LPIPS is
    absent and the log says it once; with a weights file, every view has its LPIPS."""
    from nerf_lightning.outputs.evaluation import evaluate_checkpoint
    from tests.outputs.test_lpips import written_weights

    run = tmp_path / "trained"
    train(make_config("experiment=fast", "model.field.encoding.n_levels=2", "model.field.encoding.log2_table_size=10", "model.field.encoding.max_resolution=32",
                      "model.sampler.grid.resolution=8", "data.batch_size=64", "trainer.max_steps=2", "data.val_steps=[]",
                      *QUIET, run_dir=run))
    ckpt = run / "checkpoints" / "last.ckpt"
    monkeypatch.setenv("TORCH_HOME", str(tmp_path / "empty_torch_home"))  # no AlexNet weights in its hub cache
    monkeypatch.delenv("NERF_LIGHTNING_LPIPS", raising=False)  # nor named for every command
    with caplog.at_level(logging.WARNING):
        said = evaluate_checkpoint(ckpt, tmp_path / "without", max_views=2)
    assert "lpips" not in said["mean"] and said["lpips"]["skipped"].startswith("LPIPS skipped: no AlexNet weights")
    assert json.loads((tmp_path / "without" / "eval.json").read_text())["lpips"] == said["lpips"]
    assert sum("LPIPS skipped" in record.getMessage() for record in caplog.records) == 1

    weights = written_weights(tmp_path / "lpips.pth")
    said = evaluate_checkpoint(ckpt, tmp_path / "with", max_views=2, lpips_weights=weights)
    assert said["lpips"] == {"network": "LPIPS 0.1, AlexNet", "weights": str(weights)}
    assert said["mean"]["lpips"] > 0.0 and len(said["per_view"]) == 2 and all(row["lpips"] > 0.0 for row in said["per_view"])
