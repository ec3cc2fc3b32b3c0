"""Shared fixtures: the shipped Hydra configs composed with tiny overrides, and helpers to run the CLIs."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest

from nerf_lightning.config import compose_config

ROOT = Path(__file__).resolve().parents[1]
SHARED_DATA = ROOT.parent / "shared" / "data"


@pytest.fixture
def make_config(tmp_path):
    """compose the real train.yaml with the given overrides, writing into a fresh run folder."""

    def make(*overrides: str, run_dir: Path | None = None):
        run_dir = run_dir or tmp_path / "run"
        return compose_config([*overrides, f"paths.output_dir={run_dir}"])

    return make


def run_cli(module: str, *args: str, cwd: Path) -> subprocess.CompletedProcess:
    """Run ``python -m nerf_lightning.<module> args`` as a user would; fails the test with its output."""
    env = dict(os.environ, PYTHONUNBUFFERED="1")
    result = subprocess.run(
        [sys.executable, "-m", f"nerf_lightning.cli.{module}", *args], cwd=cwd, env=env, capture_output=True, text=True, timeout=600
    )
    if result.returncode != 0:
        pytest.fail(f"{module} {' '.join(args)} exited {result.returncode}\n{result.stdout[-3000:]}\n{result.stderr[-3000:]}")
    return result


@pytest.fixture(scope="session")
def scene_cache(tmp_path_factory):
    """A cache folder for the procedural scene shared by the whole test session (not ~/.cache)."""
    return tmp_path_factory.mktemp("scene_cache")


@pytest.fixture(scope="session")
def procedural_scene(scene_cache):
    from nerf_lightning.data.formats import load_procedural

    return load_procedural(cache_dir=scene_cache)
