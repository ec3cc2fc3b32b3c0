"""Reports of a multirun sweep: a markdown table of every job's overrides and final PSNR, and one plot (nerf-sweep-report).

Reads each job folder's ``.hydra/overrides.yaml``, ``metrics.json`` and ``psnr_history.json``; writes
``report.md`` and ``psnr.png`` into the multirun folder and prints the table.
"""

from __future__ import annotations

import json
from pathlib import Path

from omegaconf import OmegaConf

from nerf_lightning.training.callbacks import history_psnr
from nerf_lightning.io import write_atomic
from nerf_lightning.outputs.plots import plot_psnr_curves


def find_jobs(sweep_dir: Path) -> list[Path]:
    """Job folders (those with a metrics.json) under ``sweep_dir``, in job order."""
    jobs = [path.parent for path in sweep_dir.glob("*/metrics.json")]
    return sorted(jobs, key=lambda job: (not job.name.isdigit(), int(job.name) if job.name.isdigit() else 0, job.name))


def job_overrides(job: Path) -> list[str]:
    path = job / ".hydra" / "overrides.yaml"
    return list(OmegaConf.load(path)) if path.is_file() else []


def swept(overrides: list[list[str]]) -> list[list[str]]:
    """Each job's overrides reduced to those that differ between jobs: what the sweep varied."""
    common = set.intersection(*(set(job) for job in overrides)) if overrides else set()
    return [[item for item in job if item not in common] for job in overrides]


def report(sweep_dir: str | Path) -> str:
    """Write ``report.md`` and ``psnr.png`` into ``sweep_dir``; returns the markdown."""
    sweep_dir = Path(sweep_dir)
    if not sweep_dir.is_dir():
        raise FileNotFoundError(f"multirun folder not found: {sweep_dir}")
    jobs = find_jobs(sweep_dir)
    if not jobs:
        raise ValueError(f"no finished jobs in {sweep_dir}: expected <job>/metrics.json in its subfolders")
    rows = ["| job | overrides | val/psnr (dB) | train/psnr (dB) | steps | wall (s) |", "|---|---|---|---|---|---|"]
    curves = {}
    overrides_of_jobs = [job_overrides(job) for job in jobs]
    for job, overrides, varied in zip(jobs, overrides_of_jobs, swept(overrides_of_jobs)):
        metrics = json.loads((job / "metrics.json").read_text())

        def cell(key: str, digits: int = 2) -> str:
            return f"{metrics[key]:.{digits}f}" if key in metrics else "-"

        rows.append(f"| {job.name} | `{' '.join(overrides)}` | {cell('val/psnr')} | {cell('train/psnr')} | {metrics.get('step', '-')} | {cell('wall_seconds', 1)} |")
        history_path = job / "psnr_history.json"
        if history_path.is_file():
            curves[f"{job.name}: {' '.join(varied) or 'no overrides'}"] = history_psnr(json.loads(history_path.read_text()))
    markdown = f"# Sweep {sweep_dir.name}\n\n" + "\n".join(rows) + "\n\n![PSNR of every job](psnr.png)\n"
    write_atomic(sweep_dir / "report.md", markdown.encode())
    plot_psnr_curves(curves, sweep_dir / "psnr.png", title=f"validation PSNR: {sweep_dir.name}")
    return markdown
