"""nerf_lightning.training: determinism, kill -9 then resume, Lightning DDP on two CPU processes, a quiet log."""

from __future__ import annotations

import json
import math
import os
import signal
import subprocess
import sys
import time

import pytest
import torch

from nerf_lightning.checkpoints import load_model
from nerf_lightning.config import compose_config
from nerf_lightning.training import train
from tests.conftest import run_cli

# experiment=fast, small enough for a test: 120 steps of 256 rays, last.ckpt every 20 steps (not by time); on the CPU,
# whatever the machine has: these runs are compared bit for bit, which GPU atomics (index_add) do not promise
SMALL_FAST = ["experiment=fast", "trainer.accelerator=cpu", "callbacks.last_checkpoint.train_time_interval=null", "model.field.encoding.n_levels=4", "model.field.encoding.log2_table_size=12", "model.field.encoding.max_resolution=64",
              "model.sampler.grid.resolution=16", "data.batch_size=256", "data.val_views=1", "data.val_every=120",
              "trainer.max_steps=120", "callbacks.last_checkpoint.every_n_train_steps=20",
              "trainer.enable_progress_bar=false", "trainer.enable_model_summary=false"]

TINY_IMAGE_RUN = ["experiment=image", "data.downscale=8", "data.batch_size=64", "trainer.max_steps=2", "data.val_steps=[]",
                  "trainer.enable_progress_bar=false"]


@pytest.fixture
def cached_scene(scene_cache, monkeypatch):
    monkeypatch.setenv("NERF_LIGHTNING_CACHE", str(scene_cache))  # the subprocesses find the procedural scene here too


def without_clock(metrics: dict) -> dict:
    return {key: value for key, value in metrics.items() if key != "wall_seconds"}


def test_the_same_seed_gives_the_same_metrics_from_memory_or_memory_mapped_images(cached_scene, tmp_path):
    short = [*SMALL_FAST, "trainer.max_steps=60", "data.val_every=60"]  # half the runs of the other tests: three of them here
    first = train(compose_config([*short, f"paths.output_dir={tmp_path / 'a'}"]))
    second = train(compose_config([*short, f"data.scene.image_cache={tmp_path / 'images'}", f"paths.output_dir={tmp_path / 'b'}"]))
    assert len(list((tmp_path / "images").glob("*.u8"))) == 3  # train, val and test were mapped from files
    saved = [json.loads((tmp_path / run / "metrics.json").read_text()) for run in ("a", "b")]
    assert without_clock(saved[0]) == without_clock(saved[1]) and without_clock(first) == without_clock(second)
    histories = [json.loads((tmp_path / run / "psnr_history.json").read_text()) for run in ("a", "b")]
    assert histories[0]["train_psnr"] == histories[1]["train_psnr"]
    other_seed = train(compose_config([*short, "seed=1", f"paths.output_dir={tmp_path / 'c'}"]))
    assert other_seed["train/loss"] != first["train/loss"]  # the seed does reach the weights and the rays


def test_the_same_seed_gives_the_same_metrics_for_splats_drawn_by_the_tile_rasteriser(cached_scene, tmp_path):
    # the tile rasteriser's threads each add into their own slots, summed in a fixed order: no race reaches the weights
    small = ["experiment=splat_procedural", "trainer.accelerator=cpu", "data.scene.size=32", "model.start.random.count=2000",
             "model/rasterizer=tiles", "trainer.max_steps=60", "data.val_every=60", "data.val_views=1",
             "model.strategy.refine_start=20", "model.strategy.refine_every=20", "trainer.enable_progress_bar=false",
             "trainer.enable_model_summary=false"]
    runs = [train(compose_config([*small, f"paths.output_dir={tmp_path / run}"])) for run in ("a", "b")]
    saved = [json.loads((tmp_path / run / "metrics.json").read_text()) for run in ("a", "b")]
    assert without_clock(saved[0]) == without_clock(saved[1]) and without_clock(runs[0]) == without_clock(runs[1])
    assert saved[0]["train/gaussians"] != 2000  # the strategy grew or pruned them: its gradients took part


def step_of(checkpoint) -> int:
    return int(torch.load(checkpoint, weights_only=False, map_location="cpu")["global_step"])


def test_kill_9_mid_run_then_resume_ends_where_the_uninterrupted_run_does(cached_scene, tmp_path):
    straight = train(compose_config([*SMALL_FAST, f"paths.output_dir={tmp_path / 'straight'}"]))

    killed = tmp_path / "killed"
    last = killed / "checkpoints" / "last.ckpt"
    process = subprocess.Popen([sys.executable, "-m", "nerf_lightning.cli.train", *SMALL_FAST, f"hydra.run.dir={killed}"],
                               cwd=tmp_path, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True, env=dict(os.environ))
    try:
        deadline = time.monotonic() + 240
        while not (last.exists() and step_of(last) >= 40):
            assert process.poll() is None, f"training ended before it was killed:\n{process.stderr.read()[-2000:]}"
            assert time.monotonic() < deadline, "no checkpoint at step 40 in time"
            time.sleep(0.05)
        process.send_signal(signal.SIGKILL)
        process.wait(timeout=60)
    finally:
        process.kill()
    assert process.returncode == -signal.SIGKILL
    saved_step = step_of(last)  # whole: written through a temporary file and a rename
    assert 40 <= saved_step < 120 and not list(last.parent.glob("*.tmp"))

    resumed = train(compose_config([*SMALL_FAST, f"ckpt_path={last}", f"paths.output_dir={tmp_path / 'resumed'}"]))
    assert resumed["step"] == 120
    # the same optimiser state, learning rate, occupancy grid, batches (seeded by step) and jitter (torch's random
    # state is in the checkpoint): the resumed run ends where the uninterrupted one does
    assert resumed["val/psnr"] == pytest.approx(straight["val/psnr"], abs=0.05)
    assert resumed["lr-Adam"] == pytest.approx(straight["lr-Adam"], rel=1e-6)
    grids = [load_model(run / "checkpoints" / "last.ckpt")[0].sampler.grid.binary for run in (tmp_path / "straight", tmp_path / "resumed")]
    assert float((grids[0] != grids[1]).float().mean()) < 0.02


def test_ddp_trains_on_two_cpu_processes_and_its_checkpoint_loads(cached_scene, tmp_path):
    run = tmp_path / "ddp"
    result = subprocess.run(
        [sys.executable, "-m", "nerf_lightning.cli.train", *SMALL_FAST, "trainer=ddp", "trainer.devices=2",
         "trainer.max_steps=6", "data.val_every=6", f"hydra.run.dir={run}"],
        cwd=tmp_path, capture_output=True, text=True, timeout=300,
    )
    assert result.returncode == 0, result.stderr[-3000:]
    output = result.stdout + result.stderr
    assert "MEMBER: 1/2" in output and "MEMBER: 2/2" in output  # both processes joined
    model, info = load_model(run / "checkpoints" / "last.ckpt")
    assert info["global_step"] == 6 and info["config"]["trainer"]["strategy"] == "ddp"
    metrics = json.loads((run / "metrics.json").read_text())
    assert metrics["step"] == 6 and "val/psnr" in metrics


def test_nerf_train_prints_no_lightning_cloud_adverts(tmp_path):
    """Lightning logs a litlogger tip on every run, and a litmodels one when it adds its own ModelCheckpoint
    (callbacks=none); nerf_lightning.training filters both out of its log, nothing else."""
    result = run_cli("train", *TINY_IMAGE_RUN, "callbacks=none", f"hydra.run.dir={tmp_path / 'run'}", cwd=tmp_path)
    output = result.stdout + result.stderr
    assert "GPU available" in output  # Lightning's other info lines still show
    assert "litmodels" not in output and "litlogger" not in output and "💡" not in output


# a splat run (0.8 L1 + 0.2 D-SSIM) and a proposal run (interlevel and distortion terms): neither loss is an MSE
CURVE_RUNS = {
    "splats": ["experiment=splat_procedural", "data.scene.size=32", "model.start.random.count=2000", "trainer.max_steps=20"],
    "proposal": [*(o for o in SMALL_FAST if not o.startswith("model.sampler.")), "model/sampler=proposal", "~model.sampler.grid",
                 "~model.sampler.step_size",
                 "model.sampler.proposal_samples=[32,16]", "model.sampler.field_samples=8", "trainer.max_steps=20"],
}


@pytest.mark.parametrize("run", list(CURVE_RUNS))
def test_the_runs_psnr_curve_is_the_psnr_tensorboard_shows(run, cached_scene, tmp_path):
    from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

    train(compose_config([*CURVE_RUNS[run], "trainer.log_every_n_steps=5", "data.val_every=null", "trainer.enable_progress_bar=false",
                          "trainer.enable_model_summary=false", f"paths.output_dir={tmp_path}"]))
    history = json.loads((tmp_path / "psnr_history.json").read_text())
    events = EventAccumulator(str(tmp_path / "tensorboard"), size_guidance={"scalars": 0})
    events.Reload()
    logged = [event.value for event in events.Scalars("train/psnr")]
    losses = [event.value for event in events.Scalars("train/loss")]
    assert len(history["train_psnr"]) == len(logged) == 4
    # the curve's points are the logged PSNRs, the MSE's, and not the PSNR the total loss would give
    assert history["train_psnr"] == pytest.approx(logged, abs=1e-4)
    assert all(abs(psnr + 10.0 * math.log10(loss)) > 0.05 for psnr, loss in zip(history["train_psnr"], losses))
