"""nerf-sweep-report on the folder of a nerf-train multirun sweep."""

import json

import yaml

from tests.cli.test_train import TINY
from tests.conftest import assert_curves_drawn, run_cli


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
    assert_curves_drawn(sweep / "psnr.png", curves=2)  # one a job
