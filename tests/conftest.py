"""Shared fixtures: the shipped Hydra configs composed with tiny overrides, and helpers to run the CLIs."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest
import torch

# Without a GPU, Triton's kernels (the splats' GPU rasteriser) run in Triton's interpreter over numpy, which is how
# their tests check them here. Triton reads this when it is first imported (lightning imports it), so before anything.
if not torch.cuda.is_available():
    os.environ.setdefault("TRITON_INTERPRET", "1")

from nerf_lightning.config import compose_config  # noqa: E402

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


# matplotlib's first colours (tab10), in the order a plot's curves take them
CURVE_COLOURS = ((31, 119, 180), (255, 127, 14), (44, 160, 44), (214, 39, 40))


def assert_curves_drawn(path: Path, curves: int = 1) -> None:
    """A PSNR plot (:func:`nerf_lightning.outputs.plots.plot_psnr_curves`) that draws ``curves`` curves: a PNG of a figure's
    size, with each of the first ``curves`` line colours on enough pixels to be a line, and no more curves than that."""
    import imageio.v3 as iio
    import numpy as np

    image = iio.imread(path)[..., :3].astype(np.int16)
    assert image.shape[0] > 200 and image.shape[1] > 300, f"{path}: {image.shape} is no figure"

    def pixels_of(colour):
        return int((np.abs(image - np.array(colour)).max(axis=-1) < 30).sum())

    for index, colour in enumerate(CURVE_COLOURS):
        if index < curves:
            assert pixels_of(colour) > 100, f"{path}: curve {index + 1} (colour {colour}) is not drawn"
        else:
            assert pixels_of(colour) < 20, f"{path}: a curve {index + 1} (colour {colour}) is drawn, {curves} expected"
