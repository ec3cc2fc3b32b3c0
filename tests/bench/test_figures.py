"""The figures a benchmark row carries beside its PSNR: samples and rays a step, Gaussians, the peak GPU memory (CUDA
only, from nerf-train's metrics.json), and the suite as it was given to nerf-bench."""

from __future__ import annotations

import torch

from nerf_lightning.bench.runner import step_figures, suite_argument
from nerf_lightning.bench.suite import load_suite
from nerf_lightning.devices import peak_memory_gb
from tests.conftest import ROOT


def test_the_peak_memory_is_cudas_and_none_elsewhere(monkeypatch):
    assert peak_memory_gb(torch.device("cpu")) is None and peak_memory_gb(torch.device("mps")) is None
    asked = []
    monkeypatch.setattr(torch.cuda, "max_memory_allocated", lambda device: asked.append(device) or 3 * 2**30 + 2**29)
    assert peak_memory_gb(torch.device("cuda", 0)) == 3.5 and asked == [torch.device("cuda", 0)]


def test_a_rows_step_figures_come_from_the_runs_metrics():
    radiance = {"train/samples_per_ray": 12.5, "train/rays": 20480.0, "train/psnr": 30.0, "peak_memory_gb": 7.25}
    assert step_figures(radiance) == {"samples_per_ray": 12.5, "rays_per_step": 20480.0, "samples_per_step": 256000,
                                      "gaussians": None, "peak_memory_gb": 7.25}
    splats = {"train/gaussians": 250000.0, "train/psnr": 28.0}  # on a CPU: no peak memory
    assert step_figures(splats) == {"samples_per_ray": None, "rays_per_step": None, "samples_per_step": None,
                                    "gaussians": 250000.0, "peak_memory_gb": None}


def test_a_suite_is_named_as_it_was_given(tmp_path):
    assert suite_argument(load_suite("cpu-quick")) == "cpu-quick"
    own = tmp_path / "mine.yaml"
    own.write_text("device: cpu\nrows:\n  - {scene: procedural, preset: fast, minutes: 1}\n")
    assert suite_argument(load_suite(str(own))) == str(own)


def test_the_gpu_check_suite_loads_and_its_rows_compose():
    from nerf_lightning.config import compose_config

    suite = load_suite(str(ROOT / "scripts" / "gpu_check.yaml"))
    assert [row.id for row in suite.rows] == ["lego/splat_blender_gpu/2min/seed0", "fox/splat_360_gpu/2min/seed0",
                                              "lego/fast_blender_gpu/1min/seed0", "moldGoldCape/nerfacto_360_gpu/1min/seed0",
                                              "moldGoldCape/splat_object_gpu/4min/seed0"]
    assert all(row.device == "cuda" for row in suite.rows) and suite.rows[0].marks == (1.0, 2.0)
    for row in suite.rows:
        compose_config([f"experiment={row.preset}", f"data.root=/nowhere/{row.data}", *row.overrides])
    # the object's GPU preset: its CPU parent's masks and growth, on whole views
    gpu = compose_config(["experiment=splat_object_gpu", "data.root=/nowhere"])
    assert gpu.data.masks == "background" and gpu.data.patch_size is None and gpu.model.strategy.grow_grad2d == 1.0e-4
    assert gpu.model.strategy.refine_stop < gpu.trainer.max_steps


def test_the_posing_table_says_how_well_the_masks_agree_where_a_row_measured_it():
    from nerf_lightning.bench.report import posing_table

    row = {"capture": "moldGoldCape", "images": "images_4", "masks": "masks_4", "images_given": 20, "registered": 15,
           "median_position_error_percent_of_spread": 68.35, "max_position_error_percent_of_spread": 151.16,
           "median_rotation_error_deg": 79.35, "max_rotation_error_deg": 152.54, "total_s": 165.0,
           "machine": {"name": "2 cores"}, "date": "2026-11-27T18:00:00"}
    lines = posing_table([{**row, "silhouettes": {"median_coverage": 0.0, "views_below": ["a.jpg"]}}, row])
    assert lines[0].count("|") == lines[1].count("|") == lines[2].count("|") == lines[3].count("|")
    assert "| 79.35 / 152.54 | 0 % | 165 |" in lines[2]
    assert "| 79.35 / 152.54 | – | 165 |" in lines[3]  # a row from before the check
    assert lines[2].startswith("| moldGoldCape images_4/ | yes | 20 |")
    darker = posing_table([{**row, "photo_change": "dark:0.25"}])[2]
    assert darker.startswith("| moldGoldCape images_4/, photos darkened x 0.25 | yes | 20 |"), darker
    sequential = posing_table([{**row, "process_capture": {"matcher": "sequential"}}])[2]
    assert sequential.startswith("| moldGoldCape images_4/, matcher=sequential | yes | 20 |"), sequential
    assert lines[0].endswith("| revision |") and lines[3].endswith("| – |")  # no revision recorded
    revised = posing_table([{**row, "revision": "308ca46+dirty"}])[2]
    assert revised.endswith("| 2026-11-27 | `308ca46+dirty` |"), revised


def test_the_results_tables_say_how_many_views_each_row_was_scored_on_and_at_what_size():
    """docs/results.md's and the README's tables: a views column, N @ width x height from the row's JSON, – for a row
    that did not record it."""
    from nerf_lightning.bench.report import readme_table, scene_table

    row = {"suite": "cpu", "scene": "lego", "preset": "splat_blender", "minutes": 10, "training_minutes": 4.65, "steps": 900,
           "seconds_per_step": 0.3, "psnr": 34.11, "ssim": 0.986, "lpips": 0.0087, "seconds_per_frame": 0.02, "views": 5,
           "frame_size": [400, 300], "machine": {"name": "2 cores"}, "date": "2026-12-07T14:00:00", "revision": "5d62a8f"}
    unknown = {key: value for key, value in row.items() if key not in ("views", "frame_size")}
    for table in (scene_table([row, unknown]), readme_table([row, {**unknown, "preset": "fast_blender"}])):
        header = [cell.strip() for cell in table[0].strip("|").split("|")]
        column = header.index("views (WxH)")
        cells = [[cell.strip() for cell in line.strip("|").split("|")] for line in table[2:]]
        assert sorted(line[column] for line in cells) == ["5 @ 300x400", "–"], table
        assert all(len(line) == len(header) for line in cells)
        assert any(line[header.index("LPIPS")] == "0.009" for line in cells)
