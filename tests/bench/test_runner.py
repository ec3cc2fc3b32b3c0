"""nerf-bench run as a user runs it: a suite file's procedural row end to end (the cpu-quick suite's smallest row, cut
to a quarter of a minute so that CI keeps the runner from rotting within its time), --resume, rows without their
data, the results table regenerated from the JSON."""

from __future__ import annotations

import json
import math
import os
import subprocess
import sys
from pathlib import Path

import pytest

from tests.conftest import assert_curves_drawn

BENCH = [str(Path(sys.executable).parent / "nerf-bench")] if (Path(sys.executable).parent / "nerf-bench").exists() else [
    sys.executable, "-m", "nerf_lightning.bench.runner"]


def bench(*arguments, cwd):
    return subprocess.run([*BENCH, *arguments], cwd=cwd, capture_output=True, text=True, timeout=600)


@pytest.fixture(scope="module")
def quick_row(tmp_path_factory):
    """A suite file's one procedural row (cpu-quick's, shorter), measured once for the module. It stops at its
    max_steps, well inside its 3 minutes even where numba compiles first (a fresh clone) or another job shares the
    cores (it took over a minute so), so its PSNR does not depend on the machine's speed."""
    folder = tmp_path_factory.mktemp("bench")
    (folder / "quick.yaml").write_text("device: cpu\nrows:\n  - {scene: procedural, preset: fast, minutes: 3, marks: [0.1, 3], overrides: [trainer.max_steps=150]}\n")
    (folder / "README.md").write_text("# A project\n\n<!-- results table: nerf-bench report writes it -->\nby hand\n<!-- end of the results table -->\n\nMore.\n")
    # --allow-dirty: the tests run from a checkout being worked on
    result = bench("run", "quick.yaml", "--only", "procedural/*", "--results", "results", "--report", "results.md", "--work", "work",
                   "--readme", "README.md", "--allow-dirty", cwd=folder)
    assert result.returncode == 0, result.stdout + result.stderr
    return folder, result


def test_the_smallest_row_trains_scores_and_writes_its_json(quick_row):
    folder, result = quick_row
    results = json.loads((folder / "results" / "quick.json").read_text())
    [row] = results["rows"]
    assert row["id"] == "procedural/fast/3min/seed0" and row["suite"] == "quick"
    # trained for real: steps taken, the marks scored in order, a PSNR well above an empty picture's
    assert row["steps"] == 150 and [point["minutes"] for point in row["curve"]] == [0.1, 3]
    assert row["curve"][0]["step"] <= row["curve"][1]["step"] == row["steps"]
    assert row["training_minutes"] <= 3 + 0.1
    # the scene's mean colour scores about 10 dB on these views; its 150 steps reach about 18.6 (21 s on 2 cores)
    assert 16.0 < row["psnr"] < 60.0 and 0.0 < row["ssim"] <= 1.0
    # the colour-corrected scores beside the raw ones: a map fitted to the photo can only bring the render closer
    assert row["cc_psnr"] >= row["psnr"] - 0.05 and 0.0 < row["cc_ssim"] <= 1.0 and row["curve"][0]["cc_psnr"] is not None
    assert row["seconds_per_frame"] > 0 and row["seconds_per_step"] > 0 and math.isfinite(row["samples_per_ray"])
    # where and with what it was measured, and how to measure it again
    assert {"name", "cpu", "cores", "gpu"} <= set(row["machine"]) and row["machine"]["gpu"] is None
    assert {"torch", "lightning", "nerf-lightning"} <= set(row["versions"]) and row["date"][:2] == "20"
    assert row["commands"]["train"].startswith("nerf-train experiment=fast seed=0")
    assert row["commands"]["bench"] == "nerf-bench run quick.yaml --only procedural/fast/3min/seed0"
    assert "Traceback" not in result.stderr
    # the commit as the row started (this test's checkout may be dirty: --allow-dirty)
    assert row["revision"] is None or row["revision"].split("+")[0].isalnum()


def test_the_results_table_and_plot_are_generated(quick_row):
    folder, _ = quick_row
    report = (folder / "results.md").read_text()
    assert "## procedural" in report and "| quick | fast | " in report
    assert "colour-corrected PSNR / SSIM / LPIPS" in report and " / – |" in report  # LPIPS where its weights are
    assert "![procedural: held-out PSNR against training minutes](results/procedural.png)" in report
    assert_curves_drawn(folder / "results" / "procedural.png", curves=1)
    assert "nerf-bench run quick.yaml --only procedural/fast/3min/seed0" in report
    # the rows not measured here are listed, with the command that measures them
    assert "## Not measured yet" in report and "`nerf-bench run gpu`" in report
    # regenerating from the JSON gives the same page
    (folder / "results.md").unlink()
    assert bench("report", "--results", "results", "--report", "results.md", cwd=folder).returncode == 0
    assert (folder / "results.md").read_text() == report


def test_a_rows_kept_checkpoint_is_scored_again_and_a_row_without_one_is_named(quick_row):
    folder, _ = quick_row
    results = folder / "results" / "quick.json"
    before = json.loads(results.read_text())["rows"][0]
    stripped = {**before, **{key: None for key in ("cc_psnr", "cc_ssim", "cc_lpips", "cc_psnr_masked")}}  # a row scored before them
    gone = {**before, "id": "procedural/fast/9min/seed0", "commands": {**before["commands"], "eval": "nerf-eval ckpt_path=work/gone.ckpt"}}
    results.write_text(json.dumps({"suite": "quick", "rows": [stripped, gone]}))
    result = bench("rescore", "quick.yaml", "--results", "results", "--report", "results.md", "--work", "work", cwd=folder)
    assert result.returncode == 0, result.stdout + result.stderr
    assert "[procedural/fast/9min/seed0, " in result.stdout and "work/gone.ckpt is not here" in result.stdout
    rows = {row["id"]: row for row in json.loads(results.read_text())["rows"]}
    row = rows["procedural/fast/3min/seed0"]
    # the same checkpoint and views: the raw scores as before, the colour-corrected ones back, the training figures kept
    assert row["psnr"] == pytest.approx(before["psnr"], abs=1e-3) and row["rescored"]["psnr_as_before"]
    assert row["cc_psnr"] == pytest.approx(before["cc_psnr"], abs=1e-3) and row["curve"][-1]["cc_psnr"] == row["cc_psnr"]
    assert (row["steps"], row["seconds_per_step"], row["date"]) == (before["steps"], before["seconds_per_step"], before["date"])
    assert "rescored" not in rows["procedural/fast/9min/seed0"]
    results.write_text(json.dumps({"suite": "quick", "rows": [before]}))  # as the other tests of the module expect it


def test_rows_kept_outside_docs_results_leave_the_readmes_table_alone(quick_row, tmp_path):
    """A run or report into another results folder (a GPU lease's, a smoke run's) does not replace the README's table
    with its own rows; --readme names one to write."""
    folder, _ = quick_row
    readme = tmp_path / "README.md"
    text = "# A project\n\n<!-- results table: nerf-bench report writes it -->\nby hand\n<!-- end of the results table -->\n"
    readme.write_text(text)
    results = folder / "results"
    assert bench("report", "--results", str(results), "--report", str(tmp_path / "results.md"), cwd=tmp_path).returncode == 0
    assert readme.read_text() == text
    assert bench("report", "--results", str(results), "--report", str(tmp_path / "results.md"), "--readme", "README.md",
                 cwd=tmp_path).returncode == 0
    assert "by hand" not in readme.read_text()
    # without --report, another folder's page goes beside it, not into docs/results.md
    assert bench("report", "--results", str(results), cwd=tmp_path).returncode == 0
    assert results.with_suffix(".md").is_file() and not (tmp_path / "docs").exists()


def test_the_projects_own_results_write_its_page_and_readme_by_default(quick_row, tmp_path):
    """nerf-bench report with no arguments, in a checkout: docs/results/*.json -> docs/results.md and the README's
    table (given as ./docs/results too, the same folder)."""
    import shutil

    folder, _ = quick_row
    shutil.copytree(folder / "results", tmp_path / "docs" / "results")
    readme = tmp_path / "README.md"
    readme.write_text("# A project\n\n<!-- results table: nerf-bench report writes it -->\nby hand\n<!-- end of the results table -->\n")
    assert bench("report", cwd=tmp_path).returncode == 0
    assert "## procedural" in (tmp_path / "docs" / "results.md").read_text()
    # the README's table holds the cpu suite's rows (none here): regenerated, the hand-written line gone
    assert "by hand" not in readme.read_text()
    readme.write_text(readme.read_text().replace("| scene | preset |", "by hand\n| scene | preset |"))
    assert bench("report", "--results", "./docs/results", cwd=tmp_path).returncode == 0
    assert "by hand" not in readme.read_text()


def test_the_readmes_table_is_regenerated_between_its_marker_lines(quick_row):
    folder, _ = quick_row
    readme = (folder / "README.md").read_text()
    assert readme.startswith("# A project\n\n") and readme.endswith("<!-- end of the results table -->\n\nMore.\n")
    assert "by hand" not in readme and "| scene | preset | training minutes | views (WxH) | PSNR |" in readme


def test_a_checkout_with_uncommitted_changes_is_refused_unless_allowed(tmp_path, monkeypatch):
    from nerf_lightning.bench import machine, runner
    from nerf_lightning.bench.suite import load_suite

    monkeypatch.setattr(machine, "source_revision", lambda ignore=(): "abc1234+dirty")
    suite_file = tmp_path / "quick.yaml"
    suite_file.write_text("device: cpu\nrows:\n  - {scene: procedural, preset: fast, minutes: 0.25}\n")
    suite = load_suite(str(suite_file))
    with pytest.raises(runner.BenchmarkError, match=r"uncommitted changes \(at abc1234\+dirty\).*--allow-dirty"):
        runner.run_suite(suite, suite.rows, tmp_path, tmp_path / "results", tmp_path / "work")
    assert not (tmp_path / "results").exists() and not (tmp_path / "work").exists()


def test_resume_skips_a_row_measured_on_this_machine(quick_row):
    folder, _ = quick_row
    result = bench("run", "quick.yaml", "--only", "procedural/*", "--resume", "--allow-dirty", "--results", "results", "--report", "results.md",
                   "--work", "work", cwd=folder)
    assert result.returncode == 0 and "skipped (--resume)" in result.stdout


def test_a_row_without_its_data_is_skipped_with_a_line(tmp_path):
    result = bench("run", "cpu", "--only", "lego/*", "--data-dir", str(tmp_path / "nowhere"), "--results", "results", cwd=tmp_path)
    assert result.returncode == 0
    assert f"skipped: {tmp_path / 'nowhere' / 'nerf_synthetic' / 'lego'} not found" in result.stdout
    assert not (tmp_path / "results").exists()


def test_bad_arguments_are_answered_in_one_line(tmp_path):
    result = bench("run", "cpu", "--only", "chair/*", cwd=tmp_path)
    assert result.returncode == 2 and "Traceback" not in result.stderr
    assert "--only chair/* matches no row of suite 'cpu'" in result.stderr
    (tmp_path / "results").mkdir()
    (tmp_path / "results" / "cpu.json").write_text("{not json")
    result = bench("report", "--results", "results", cwd=tmp_path)
    assert result.returncode == 2 and "results/cpu.json is not a results JSON" in result.stderr


def test_what_the_runner_writes_does_not_make_the_checkout_dirty(tmp_path):
    from nerf_lightning.bench.machine import changed_files

    status = " M docs/results/cpu.json\n M README.md\n M nerf_lightning/models/splat.py\nR  a.py -> docs/results.md\n"
    written = [tmp_path / "docs" / "results", tmp_path / "README.md", tmp_path / "docs" / "results.md"]
    assert changed_files(status, tmp_path, written) == [(tmp_path / "nerf_lightning" / "models" / "splat.py").resolve()]
    assert len(changed_files(status, tmp_path)) == 4


def test_lpips_weights_named_once_reach_every_nerf_eval_the_runner_starts(tmp_path, monkeypatch):
    """--lpips-weights sets the variable nerf-eval reads (its children inherit it; the rows' commands stay as typed);
    a path that is not there is one line naming the option, exit 2."""
    from nerf_lightning.bench.runner import BenchmarkError, name_lpips_weights
    from nerf_lightning.outputs.choices import LPIPS_WEIGHTS_VARIABLE

    # set, then removed, so that monkeypatch restores the variable as it was (absent too) after name_lpips_weights sets it
    monkeypatch.setenv(LPIPS_WEIGHTS_VARIABLE, "")
    monkeypatch.delenv(LPIPS_WEIGHTS_VARIABLE)
    name_lpips_weights(None)
    assert LPIPS_WEIGHTS_VARIABLE not in os.environ
    (tmp_path / "lpips").mkdir()
    monkeypatch.chdir(tmp_path)
    name_lpips_weights(Path("lpips"))
    assert os.environ[LPIPS_WEIGHTS_VARIABLE] == str(tmp_path / "lpips")
    with pytest.raises(BenchmarkError, match="--lpips-weights: no such file or folder nowhere"):
        name_lpips_weights(Path("nowhere"))
    result = bench("rescore", "cpu", "--results", "results", "--lpips-weights", "nowhere", cwd=tmp_path)
    assert result.returncode == 2 and result.stderr.strip() == "nerf-bench: --lpips-weights: no such file or folder nowhere"
