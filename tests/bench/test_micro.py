"""The micro-benchmarks: nerf_lightning.bench.micro's timing, skipping and JSON, and each script of scripts/ run once as
a user runs it, on the procedural scene at its smallest (no ../shared/data needed; process-data skips without fox or
pycolmap)."""

from __future__ import annotations

import json
import math
import os
import subprocess
import sys
from itertools import count
from pathlib import Path
from types import SimpleNamespace

import pytest
import torch

from nerf_lightning.bench import micro
from nerf_lightning.training import train
from tests.conftest import ROOT

PROVENANCE = ("machine", "versions", "revision", "date", "command")


# -- the timing helper ---------------------------------------------------------------------------------------------


@pytest.fixture(scope="module")
def small_scene_cache(tmp_path_factory):
    """A scene cache of this module's own for its 16-pixel procedural scenes: the session's ``scene_cache`` holds the
    one default-sized scene that other tests find by its name."""
    return tmp_path_factory.mktemp("small_scene_cache")

def test_summarize_gives_the_median_and_the_spread():
    summary = micro.summarize([4.0, 1.0, 3.0, 2.0, 5.0])
    assert summary["median_s"] == 3.0 and summary["mean_s"] == 3.0 and (summary["min_s"], summary["max_s"]) == (1.0, 5.0)
    assert summary["iqr_s"] == pytest.approx(2.0) and summary["stdev_s"] == pytest.approx(math.sqrt(2.5))
    assert summary["repeats"] == 5 and summary["all_s"] == [4.0, 1.0, 3.0, 2.0, 5.0]
    one = micro.summarize([0.5])
    assert one["median_s"] == 0.5 and one["iqr_s"] == 0.0 and one["stdev_s"] == 0.0
    with pytest.raises(ValueError):
        micro.summarize([])


def test_time_call_warms_up_untimed_then_times_each_repeat():
    ticks = count()
    calls = []
    # the fake clock advances 1 at each read and the call itself reads it once more: every call lasts 2 ticks
    clock = lambda: float(next(ticks))  # noqa: E731
    result = micro.time_call(lambda: calls.append(clock()), repeats=4, warmup=2, clock=clock)
    assert len(calls) == 6
    assert result["repeats"] == 4 and result["all_s"] == [2.0] * 4 and result["median_s"] == 2.0
    assert result["warmup_s"] == [2.0, 2.0]
    with pytest.raises(ValueError):
        micro.time_call(lambda: None, repeats=0)


def test_time_call_waits_for_the_device_around_each_call(monkeypatch):
    events = []
    monkeypatch.setattr(micro, "synchronize", lambda device: events.append(("sync", device.type)))
    micro.time_call(lambda: events.append("call"), repeats=2, warmup=1, device="cpu")
    assert events == [("sync", "cpu"), "call", ("sync", "cpu")] * 3
    events.clear()
    micro.time_call(lambda: events.append("call"), repeats=2, warmup=0)  # no device: nothing to wait for
    assert events == ["call", "call"]


def test_step_timer_times_the_steps_after_its_warm_up(tmp_path):
    path = tmp_path / "steps.json"
    timer = micro.StepTimer(warmup_steps=2, path=str(path))
    trainer = SimpleNamespace(global_step=0, is_global_zero=True)
    module = SimpleNamespace(device=torch.device("cpu"))
    for _ in range(5):
        timer.on_train_batch_start(trainer, module, None, 0)
        trainer.global_step += 1  # the optimiser step
        timer.on_train_batch_end(trainer, module, None, None, 0)
    timer.on_train_end(trainer, module)
    written = json.loads(path.read_text())
    assert len(written["step_s"]) == 3 and len(written["loop_s"]) == 3 and written["device"] == "cpu"
    assert all(seconds >= 0 for seconds in written["step_s"] + written["loop_s"])
    with pytest.raises(ValueError):
        micro.StepTimer(warmup_steps=-1)


# -- skipping and the JSON -----------------------------------------------------------------------------------------

def test_skip_prints_why_and_exits_0(capsys, tmp_path):
    with pytest.raises(SystemExit) as exited:
        micro.require_path(tmp_path / "absent", "data")
    assert exited.value.code == 0
    assert json.loads(capsys.readouterr().out) == {"skipped": f"data not found: {tmp_path / 'absent'}"}


def test_the_json_starts_with_provenance_and_the_command_line(tmp_path, capsys, monkeypatch):
    monkeypatch.setattr(sys, "argv", ["scripts/bench_x.py", "--out", "x.json"])
    result = {**micro.start_result("cpu"), "figure": float("nan")}
    assert list(result)[:5] == list(PROVENANCE) and result["command"] == ["scripts/bench_x.py", "--out", "x.json"]
    assert result["machine"]["gpu"] is None
    micro.finish(result, tmp_path / "out" / "result.json")
    written = json.loads((tmp_path / "out" / "result.json").read_text())
    assert written == json.loads(capsys.readouterr().out) and written["figure"] is None  # NaN: null, standard JSON


def test_compose_preset_finds_its_data_or_skips(tmp_path, capsys):
    cfg, root = micro.compose_preset("fast")  # the procedural scene: no root
    assert root is None and cfg.name == "fast"
    with pytest.raises(SystemExit, match="reads no data.root"):
        micro.compose_preset("fast", root=tmp_path)
    cfg, root = micro.compose_preset("fast_blender", root=tmp_path)
    assert root == tmp_path.resolve() and cfg.data.root == str(tmp_path.resolve())
    with pytest.raises(SystemExit) as exited:
        micro.compose_preset("fast_blender", root=tmp_path / "absent")
    assert exited.value.code == 0 and "skipped" in json.loads(capsys.readouterr().out)
    cfg, root = micro.compose_preset("fast_blender", root=tmp_path / "absent", need_data=False)  # the model's settings only
    assert cfg.model.field.encoding.n_levels == 8


# -- the scripts, as a user runs them ------------------------------------------------------------------------------

def run_script(name: str, *args: str, cache: Path) -> dict:
    """``python scripts/<name> args`` from the checkout's root; its JSON (the last thing it prints)."""
    # one thread: a check that the script works, quick on a machine that is busy, not a measurement
    env = dict(os.environ, NERF_LIGHTNING_CACHE=str(cache), OMP_NUM_THREADS="1", PYTHONUNBUFFERED="1")
    result = subprocess.run([sys.executable, f"scripts/{name}", *args], cwd=ROOT, env=env, capture_output=True, text=True, timeout=300)
    assert result.returncode == 0, f"{name} exited {result.returncode}\n{result.stdout[-3000:]}\n{result.stderr[-3000:]}"
    return json.loads(result.stdout[result.stdout.index("{"):])


def assert_provenance_and_timings(result: dict, out: Path, *timings: dict) -> None:
    assert all(key in result for key in PROVENANCE), list(result)
    assert result["machine"]["name"] and result["versions"]["torch"] and isinstance(result["command"], list)
    assert json.loads(out.read_text()) == result
    for timing in timings:
        for key in ("median_s", "mean_s", "min_s"):
            assert math.isfinite(timing[key]) and timing[key] > 0, (key, timing)


def test_hash_encoding_benchmark(tmp_path, small_scene_cache):
    out = tmp_path / "hash.json"
    result = run_script("bench_hash_encoding.py", "--preset", "fast", "--points", "2048", "--repeats", "2", "--warmup", "1",
                        "--device", "cpu", "--out", str(out), "--", "model.field.encoding.compile_evaluation=false", cache=small_scene_cache)
    assert_provenance_and_timings(result, out, result["forward"], result["forward_backward"])
    assert result["settings"]["n_levels"] == 8 and result["points"] == 2048 and result["forward_compiled"] is False
    reference = result["reference"]
    assert_provenance_and_timings(result, out, reference["forward"], reference["forward_backward"])
    assert reference["max_abs_difference"] < 1e-5


def test_train_step_benchmark_runs_the_library_training_step(tmp_path, small_scene_cache):
    out = tmp_path / "train_step.json"
    result = run_script("bench_train_step.py", "--preset", "fast", "--steps", "3", "--warmup", "1", "--device", "cpu", "--out", str(out),
                        "--", "data.scene.size=16", "data.batch_size=64", "model.sampler.grid.resolution=32",
                        "model.field.encoding.compile_evaluation=false", cache=small_scene_cache)
    assert_provenance_and_timings(result, out, result["step"], result["loop"])
    assert result["global_step"] == 4 and result["steps"] == 3 and result["step"]["repeats"] == 3
    assert result["batch_size"] == 64 and result["rays_per_second"] > 0 and result["device"] == "cpu"
    assert result["root"] is None  # the procedural scene
    assert result["callbacks"] == ["step_timer"]  # no checkpoints, snapshots or validation in the timed steps


def test_frame_benchmark_renders_a_held_out_view(tmp_path, small_scene_cache):
    out = tmp_path / "frame.json"
    result = run_script("bench_frame.py", "--preset", "nerf_procedural", "--scale", "0.5", "--repeats", "2", "--warmup", "1",
                        "--device", "cpu", "--out", str(out), "--", "data.scene.size=16", "model.sampler.n_samples=8", cache=small_scene_cache)
    assert_provenance_and_timings(result, out, result["frame"])
    assert (result["height"], result["width"]) == (8, 8) and result["trained"] is False and result["rays_per_second"] > 0


def test_frame_benchmark_renders_a_checkpoint(tmp_path, small_scene_cache, make_config, monkeypatch):
    monkeypatch.setenv("NERF_LIGHTNING_CACHE", str(small_scene_cache))
    train(make_config("experiment=nerf_procedural", "data.scene.size=16", "trainer.max_steps=2", "data.val_every=2", "data.val_views=1",
                      "data.batch_size=64", "model.sampler.n_samples=8", "trainer.enable_progress_bar=false", "trainer.enable_model_summary=false"))
    out = tmp_path / "frame.json"
    result = run_script("bench_frame.py", "--ckpt", str(tmp_path / "run" / "checkpoints" / "last.ckpt"), "--repeats", "2",
                        "--device", "cpu", "--out", str(out), cache=small_scene_cache)
    assert_provenance_and_timings(result, out, result["frame"])
    assert result["global_step"] == 2 and (result["height"], result["width"]) == (16, 16)


def test_frame_benchmark_skips_a_missing_checkpoint(tmp_path, small_scene_cache):
    result = run_script("bench_frame.py", "--ckpt", str(tmp_path / "absent.ckpt"), cache=small_scene_cache)
    assert result == {"skipped": f"checkpoint not found: {tmp_path / 'absent.ckpt'}"}


@pytest.mark.slow  # COLMAP on fox photos (half a minute): out of CI; tests/capture/test_process_data.py poses them there
def test_process_data_benchmark_poses_a_few_photos_or_skips(tmp_path, small_scene_cache):
    missing = run_script("bench_process_data.py", "--root", str(tmp_path / "absent"), cache=small_scene_cache)
    assert list(missing) == ["skipped"]
    out = tmp_path / "process_data.json"
    result = run_script("bench_process_data.py", "--photos", "5", "--max-size", "400", "--mapper", "incremental", "--out", str(out),
                        cache=small_scene_cache)
    if "skipped" in result:  # no fox in ../shared/data, or no pycolmap
        pytest.skip(result["skipped"])
    assert all(key in result for key in PROVENANCE) and json.loads(out.read_text()) == result
    assert result["images_given"] == 5 and result["registered"] >= 3 and result["compared_with_published"] >= 3
    assert result["seconds"]["total"] > 0 and result["settings"]["max_size"] == 400


def test_heldout_frame_draws_a_view_with_the_scores_nerf_eval_gives(tmp_path, small_scene_cache, make_config, monkeypatch):
    """scripts/heldout_frame.py: photo | render | difference over a caption whose scores are the view's in eval.json;
    a view the checkpoint does not hold is named with the ones it does."""
    from PIL import Image

    from nerf_lightning.outputs.evaluation import evaluate_checkpoint
    from tests.outputs.test_lpips import written_weights

    monkeypatch.setenv("NERF_LIGHTNING_CACHE", str(small_scene_cache))
    # 32 pixels: the smallest side AlexNet's first two poolings leave a pixel of
    train(make_config("experiment=nerf_procedural", "data.scene.size=32", "trainer.max_steps=2", "data.val_every=2", "data.val_views=1",
                      "data.batch_size=64", "model.sampler.n_samples=8", "trainer.enable_progress_bar=false", "trainer.enable_model_summary=false"))
    ckpt, weights = tmp_path / "run" / "checkpoints" / "last.ckpt", written_weights(tmp_path / "lpips.pth")
    scores = {row["view"]: row for row in evaluate_checkpoint(ckpt, tmp_path / "eval", lpips_weights=weights)["per_view"]}
    view = sorted(scores)[1]
    env = dict(os.environ, NERF_LIGHTNING_CACHE=str(small_scene_cache), OMP_NUM_THREADS="1")
    command = [sys.executable, "scripts/heldout_frame.py", str(ckpt), str(tmp_path / "frame.png"), "--lpips-weights", str(weights)]
    drawn = subprocess.run([*command, "--view", view], cwd=ROOT, env=env, capture_output=True, text=True, timeout=300)
    assert drawn.returncode == 0, drawn.stderr[-3000:]
    said = drawn.stdout.strip().splitlines()[-1]
    assert said.startswith(f"{view}: photo | render | difference x4")
    row = scores[view]
    assert f"PSNR {row['psnr']:.2f}" in said and f"SSIM {row['ssim']:.3f}" in said and f"LPIPS {row['lpips']:.4f}" in said
    assert Image.open(tmp_path / "frame.png").size == (3 * 32, 32 + 18)
    absent = subprocess.run([*command, "--view", "nope.png"], cwd=ROOT, env=env, capture_output=True, text=True, timeout=300)
    assert absent.returncode != 0 and f"--view nope.png: not a held-out view of {ckpt}" in absent.stderr and view in absent.stderr
