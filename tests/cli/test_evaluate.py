"""nerf-eval run as a user runs it."""

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
