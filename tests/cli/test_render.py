"""nerf-render run as a user runs it, on the checkpoint of a nerf-train run."""

import subprocess
import sys

import imageio.v3 as iio
import numpy as np
import torch

from tests.cli.test_train import TINY
from tests.conftest import run_cli


def test_train_then_render_from_the_checkpoint(tmp_path, make_config):
    """nerf-train's and nerf-render's own functions on their composed configs, in this process (the command lines are
    run by the other tests here)."""
    from nerf_lightning.cli.render import render
    from nerf_lightning.config import compose_config
    from nerf_lightning.training import train

    run = tmp_path / "run"
    config = make_config(*TINY, run_dir=run)
    assert config.model.field.num_frequencies == 10 and config.trainer.max_steps == 40
    train(config)

    ckpt = run / "checkpoints" / "last.ckpt"
    for scale in (1, 2, 3):
        render(compose_config([f"ckpt_path={ckpt}", f"render.scale={scale}", f"output_dir={tmp_path / f'r{scale}'}"], "render"))
    same_size = iio.imread(tmp_path / "r1" / "rgb_scale1.png")
    # the checkpoint holds the trained field: at scale 1 it renders exactly the last snapshot
    assert np.array_equal(same_size, iio.imread(run / "snapshots" / "rgb_00_step000040.png"))
    assert same_size.shape == (64, 96, 3)
    assert iio.imread(tmp_path / "r2" / "rgb_scale2.png").shape == (128, 192, 3)
    # at 3x, the centre of every third pixel (1, 4, 7, ...) is the centre of an original pixel
    triple = iio.imread(tmp_path / "r3" / "rgb_scale3.png")
    assert triple.shape == (192, 288, 3)
    difference = np.abs(triple[1::3, 1::3].astype(int) - same_size.astype(int))
    assert difference.max() <= 1  # equal up to float rounding of the positions
    assert np.abs(triple[0::3, 0::3].astype(int) - same_size.astype(int)).max() > 1  # the others are new samples


def test_render_defaults_to_the_runs_renders_folder(tmp_path):
    run = tmp_path / "run"
    run_cli("train", *TINY, "trainer.max_steps=5", "data.val_steps=[]", f"hydra.run.dir={run}", cwd=tmp_path)
    run_cli("render", f"ckpt_path={run / 'checkpoints' / 'best.ckpt'}", cwd=tmp_path)
    (written,) = list((run / "renders").glob("*/rgb_scale1.png"))
    assert iio.imread(written).shape == (64, 96, 3)


def test_render_refuses_a_file_that_is_no_nerf_train_checkpoint(tmp_path):
    torch.save({"state_dict": {}, "global_step": 3}, tmp_path / "other.ckpt")  # a Lightning checkpoint of another project
    result = subprocess.run([sys.executable, "-m", "nerf_lightning.cli.render", f"ckpt_path={tmp_path / 'other.ckpt'}",
                             f"output_dir={tmp_path / 'out'}"], cwd=tmp_path, capture_output=True, text=True, timeout=300)
    assert result.returncode == 2 and "Traceback" not in result.stderr, result.stderr[-3000:]
    lines = [line for line in result.stderr.splitlines() if line.startswith("nerf-render: error:")]
    assert len(lines) == 1 and "other.ckpt" in lines[0] and "is not a nerf-train checkpoint" in lines[0], result.stderr[-3000:]
    assert {path.name for path in (tmp_path / "out").iterdir()} <= {".hydra", "render.log"}  # Hydra's record of the run, no render
