"""The command-line tools end to end, run as a user runs them: nerf-train, nerf-render, nerf-sweep-report."""

import json

import imageio.v3 as iio
import numpy as np
import yaml

from tests.conftest import run_cli

TINY = ["experiment=image", "data.downscale=4", "data.batch_size=1024", "trainer.max_steps=40", "data.val_steps=[20]",
        "trainer.enable_progress_bar=false"]


def test_train_then_render_from_the_checkpoint(tmp_path):
    run = tmp_path / "run"
    run_cli("train", *TINY, f"hydra.run.dir={run}", cwd=tmp_path)
    config = yaml.safe_load((run / ".hydra" / "config.yaml").read_text())
    assert config["model"]["field"]["num_frequencies"] == 10 and config["trainer"]["max_steps"] == 40

    ckpt = run / "checkpoints" / "last.ckpt"
    run_cli("render", f"ckpt_path={ckpt}", f"output_dir={tmp_path / 'r1'}", cwd=tmp_path)
    run_cli("render", f"ckpt_path={ckpt}", "render.scale=2", f"output_dir={tmp_path / 'r2'}", cwd=tmp_path)
    run_cli("render", f"ckpt_path={ckpt}", "render.scale=3", f"output_dir={tmp_path / 'r3'}", cwd=tmp_path)
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


def test_multirun_sweep_and_its_report(tmp_path):
    sweep = tmp_path / "sweep"
    run_cli("train", "-m", *TINY, "model.field.num_frequencies=2,6", f"hydra.sweep.dir={sweep}", cwd=tmp_path)
    jobs = sorted(p.name for p in sweep.iterdir() if p.is_dir())
    assert jobs == ["0", "1"]
    levels = [yaml.safe_load((sweep / job / ".hydra" / "config.yaml").read_text())["model"]["field"]["num_frequencies"] for job in jobs]
    assert levels == [2, 6]

    result = run_cli("sweep_report", str(sweep), cwd=tmp_path)
    report = (sweep / "report.md").read_text()
    assert report == result.stdout.rstrip("\n") + "\n"
    rows = [line for line in report.splitlines() if line.startswith("| 0 ") or line.startswith("| 1 ")]
    assert len(rows) == 2
    for job, row in zip(jobs, rows):
        psnr = json.loads((sweep / job / "metrics.json").read_text())["val/psnr"]
        assert f"{psnr:.2f}" in row
    assert "model.field.num_frequencies=2" in rows[0] and "model.field.num_frequencies=6" in rows[1]
    assert (sweep / "psnr.png").stat().st_size > 1000


def test_ctrl_c_keeps_the_steps_done_in_last_ckpt(tmp_path):
    import signal
    import subprocess
    import sys
    import time

    import torch

    run = tmp_path / "run"
    process = subprocess.Popen(
        [sys.executable, "-X", "faulthandler", "-m", "nerf_lightning.cli.train", *TINY, "trainer.max_steps=1000000", "data.val_steps=[5]",
         "callbacks.last_checkpoint.every_n_train_steps=1000000", f"hydra.run.dir={run}"],
        cwd=tmp_path, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True,
        # a shell's background job (CI run with `&`) ignores SIGINT, and its children inherit that: give the run Ctrl-C back
        preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL),
    )
    try:
        deadline = time.monotonic() + 120
        while not (run / "psnr_history.json").exists():  # written after the validation at step 5
            assert process.poll() is None and time.monotonic() < deadline, "training did not reach its first validation"
            time.sleep(0.2)
        time.sleep(1.0)  # then let it take more steps
        process.send_signal(signal.SIGINT)
        try:
            _, stderr = process.communicate(timeout=120)
        except subprocess.TimeoutExpired:  # should it hang, say where (faulthandler dumps every thread on SIGABRT)
            process.send_signal(signal.SIGABRT)
            _, stderr = process.communicate(timeout=30)
            raise AssertionError(f"training did not stop within 120 s of Ctrl-C; where it was:\n{stderr[-6000:]}") from None
    finally:
        process.kill()
    assert process.returncode != 0
    saved = torch.load(run / "checkpoints" / "last.ckpt", weights_only=False)
    assert saved["global_step"] > 5, "Ctrl-C lost the steps after the last validation"
    assert torch.load(run / "checkpoints" / "best.ckpt", weights_only=False)["global_step"] == 5


def test_a_sweep_runs_its_jobs_in_parallel_processes(tmp_path):
    sweep = tmp_path / "sweep"
    result = run_cli("train", "-m", "hydra/launcher=parallel", *TINY, "trainer.max_steps=5", "data.val_steps=[]",
                     "model.field.num_frequencies=2,6", f"hydra.sweep.dir={sweep}", cwd=tmp_path)
    assert "Joblib.Parallel" in result.stdout + result.stderr  # the joblib launcher ran the jobs, not the basic one
    for job, level in (("0", 2), ("1", 6)):
        assert json.loads((sweep / job / "metrics.json").read_text())["step"] == 5
        assert yaml.safe_load((sweep / job / ".hydra" / "config.yaml").read_text())["model"]["field"]["num_frequencies"] == level


def test_the_slurm_preset_composes_a_submitit_launcher(tmp_path):
    result = run_cli("train", "hydra/launcher=slurm", "hydra.launcher.partition=gpu", *TINY, "--cfg", "hydra", cwd=tmp_path)
    launcher = yaml.safe_load(result.stdout)["hydra"]["launcher"]
    assert launcher["_target_"].endswith("SlurmLauncher") and launcher["partition"] == "gpu" and launcher["gpus_per_node"] == 1


def test_an_optuna_search_runs_its_trials_and_reports_the_best(tmp_path):
    import pytest

    pytest.importorskip("hydra_plugins.hydra_optuna_sweeper", reason="the optional `optuna` extra is not installed")
    sweep = tmp_path / "tune"
    result = run_cli("train", "-m", "hydra/sweeper=tune", "hydra.sweeper.n_trials=3", *TINY, "trainer.max_steps=5", "data.val_steps=[]",
                     "model.field.num_frequencies=range(2, 8)", f"hydra.sweep.dir={sweep}", cwd=tmp_path)
    assert "Best parameters" in result.stdout + result.stderr
    trials = [json.loads((sweep / str(job) / "metrics.json").read_text())["val/psnr"] for job in range(3)]
    best = yaml.safe_load((sweep / "optimization_results.yaml").read_text())
    assert best["best_value"] == max(trials)  # maximised: nerf-train returns val/psnr
