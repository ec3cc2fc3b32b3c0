"""nerf-train run as a user runs it: Ctrl-C, sweeps in parallel processes, the Slurm preset, an Optuna search."""

import json

import yaml

from tests.conftest import run_cli

TINY = ["experiment=image", "data.downscale=4", "data.batch_size=1024", "trainer.max_steps=40", "data.val_steps=[20]",
        "trainer.enable_progress_bar=false"]


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
