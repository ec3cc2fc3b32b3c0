"""What a benchmark figure was measured on: the machine (CPU model, cores, threads, GPU), the versions of the
libraries that decide the speed, and the source revision. Every JSON the runner and the micro-benchmarks write
carries this, so that a figure is only ever compared with one from the same machine."""

from __future__ import annotations

import os
import platform
import re
import subprocess
from collections.abc import Sequence
from datetime import datetime, timezone
from importlib.metadata import PackageNotFoundError, version
from pathlib import Path
from typing import Any

import torch

PACKAGES = ("nerf-lightning", "torch", "lightning", "kornia", "hydra-core")


def cpu_model() -> str:
    """The CPU's marketing name (``/proc/cpuinfo``'s model name on Linux, sysctl on a Mac), else the architecture."""
    cpuinfo = Path("/proc/cpuinfo")
    if cpuinfo.exists():
        found = re.search(r"^model name\s*:\s*(.+)$", cpuinfo.read_text(errors="replace"), flags=re.MULTILINE)
        if found:
            return found.group(1).strip()
    if platform.system() == "Darwin":
        try:
            return subprocess.run(["sysctl", "-n", "machdep.cpu.brand_string"], capture_output=True, text=True, timeout=5).stdout.strip()
        except (OSError, subprocess.SubprocessError):
            pass
    return platform.processor() or platform.machine()


def gpu_name(device: str = "auto") -> str | None:
    """The accelerator's name, or None where the figures are the CPU's (``device`` cpu, or no GPU here)."""
    if device == "cpu":
        return None
    if torch.cuda.is_available() and (device in ("auto", "cuda") or device.startswith("cuda:")):
        return torch.cuda.get_device_name(torch.device(device if device.startswith("cuda") else "cuda"))
    if device in ("auto", "mps") and torch.backends.mps.is_available():
        return f"Apple GPU ({cpu_model()})"
    return None


def source_revision(ignore: Sequence[Path] = ()) -> str | None:
    """The git commit of the checkout the package runs from (with ``+dirty`` for uncommitted changes to tracked files
    other than those under ``ignore``: what the benchmark runner writes itself), or None outside a git checkout (an
    installed wheel). Asked anew each time: a row's training runs the code the checkout has when it starts."""
    root = Path(__file__).resolve().parents[2]
    if not (root / ".git").exists():
        return None
    try:
        commit = subprocess.run(["git", "rev-parse", "--short", "HEAD"], cwd=root, capture_output=True, text=True, timeout=10).stdout.strip()
        status = subprocess.run(["git", "status", "--porcelain", "--untracked-files=no"], cwd=root, capture_output=True, text=True, timeout=10).stdout
    except (OSError, subprocess.SubprocessError):
        return None
    return f"{commit}+dirty" if commit and changed_files(status, root, ignore) else commit or None


def changed_files(status: str, root: Path, ignore: Sequence[Path] = ()) -> list[Path]:
    """The files ``git status --porcelain`` (run in ``root``) lists, less those at or under a path of ``ignore``."""
    ignored = [Path(path).resolve() for path in ignore]
    changed = [(root / line[3:].split(" -> ")[-1].strip('"')).resolve() for line in status.splitlines() if line.strip()]
    return [path for path in changed if not any(path == place or place in path.parents for place in ignored)]


def versions() -> dict[str, str]:
    """The installed versions of :data:`PACKAGES` and Python."""
    found = {"python": platform.python_version()}
    for package in PACKAGES:
        try:
            found[package] = version(package)
        except PackageNotFoundError:
            found[package] = "not installed"
    return found


def machine(device: str = "auto") -> dict[str, Any]:
    """The machine a figure is measured on: CPU model, logical cores, torch's threads, GPU (None on a CPU run), OS,
    and ``name``, one short line for the results table (``2 cores AMD EPYC 7B13`` or ``NVIDIA H100 80GB HBM3``)."""
    gpu = gpu_name(device)
    cores = os.cpu_count() or 0
    cpu = cpu_model()
    short_cpu = re.sub(r"\s+\d+-Core Processor$|\(R\)|\(TM\)|\s+CPU\s+@.*$", "", cpu).strip()
    return {
        "name": gpu or f"{cores} cores {short_cpu}", "cpu": cpu, "cores": cores, "threads": torch.get_num_threads(),
        "gpu": gpu, "os": f"{platform.system()} {platform.release()}",
    }


def now() -> str:
    """The current UTC time, ISO 8601 to the second."""
    return datetime.now(timezone.utc).replace(microsecond=0).isoformat()


def provenance(device: str = "auto", ignore: Sequence[Path] = ()) -> dict[str, Any]:
    """:func:`machine`, :func:`versions`, the revision and the date: what every benchmark JSON starts with."""
    return {"machine": machine(device), "versions": versions(), "revision": source_revision(ignore), "date": now()}
