"""Bad input and faults (docs/reliability.md) reported as nerf_lightning.errors.report_errors reports them: one clear line
naming the file or key, exit 2, nothing half-written."""

from __future__ import annotations

import json
import subprocess
import sys

import numpy as np
import pytest
import torch

from nerf_lightning.config import compose_config
from nerf_lightning.errors import report_errors
from nerf_lightning.io import write_png
from nerf_lightning.training import train
from tests.conftest import ROOT

QUIET = ["trainer.enable_progress_bar=false", "trainer.enable_model_summary=false"]


def fails_with(capsys, command: str, task, cfg, *expected: str) -> str:
    """Run ``task(cfg)`` as the command runs it; it must exit 2 with one stderr line holding every ``expected``."""
    with pytest.raises(SystemExit) as stopped:
        report_errors(command)(task)(cfg)
    assert stopped.value.code == 2
    lines = [line for line in capsys.readouterr().err.splitlines() if line.startswith(f"{command}: error:")]
    assert len(lines) == 1, lines
    for text in expected:
        assert text in lines[0], (text, lines[0])
    return lines[0]


def train_config(tmp_path, *overrides: str):
    return compose_config([*overrides, *QUIET, f"paths.output_dir={tmp_path / 'run'}"])


def blender_scene(root, count: int = 2, size: int = 8, sizes=None):
    """A minimal Blender scene: ``count`` RGB frames a split, all ``size`` pixels square unless ``sizes`` says."""
    for split in ("train", "val"):
        frames = []
        for index in range(count):
            side = (sizes or {}).get((split, index), size)
            write_png(root / split / f"r_{index}.png", torch.full((side, side, 3), 0.5))
            c2w = torch.eye(4)
            c2w[2, 3] = 4.0
            frames.append({"file_path": f"./{split}/r_{index}", "transform_matrix": c2w.tolist()})
        (root / f"transforms_{split}.json").write_text(json.dumps({"camera_angle_x": 0.69, "frames": frames}))
    return root


def test_a_missing_data_path_is_named(tmp_path, capsys):
    fails_with(capsys, "nerf-train", train, train_config(tmp_path, "experiment=fast_blender", f"data.root={tmp_path / 'nowhere'}"),
               str(tmp_path / "nowhere"), "not found")
    assert not (tmp_path / "run" / "checkpoints").exists() and not (tmp_path / "run" / "metrics.json").exists()


def test_a_required_key_left_unset_is_named(tmp_path, capsys):
    fails_with(capsys, "nerf-train", train, train_config(tmp_path, "experiment=fast_blender"), "data.root has no value", "data.root=...")


def test_an_empty_folder_says_what_it_should_hold(tmp_path, capsys):
    (tmp_path / "empty").mkdir()
    fails_with(capsys, "nerf-train", train, train_config(tmp_path, "experiment=fast_blender", f"data.root={tmp_path / 'empty'}"),
               "transforms_train.json", "expected a Blender synthetic scene")
    fails_with(capsys, "nerf-train", train, train_config(tmp_path, "experiment=fast_unbounded", f"data.root={tmp_path / 'empty'}"),
               str(tmp_path / "empty" / "transforms.json"), "not found")


@pytest.mark.parametrize("damage", ["truncated", "not_an_image"])
def test_a_corrupt_image_is_named(tmp_path, capsys, damage):
    root = blender_scene(tmp_path / "scene")
    image = root / "train" / "r_1.png"
    data = image.read_bytes()
    image.write_bytes(data[: len(data) // 2] if damage == "truncated" else b"this is no PNG")
    fails_with(capsys, "nerf-train", train, train_config(tmp_path, "experiment=fast_blender", "data.scene.downscale=1", f"data.root={root}"),
               "could not read image", str(image))


def test_images_of_different_sizes_are_named(tmp_path, capsys):
    root = blender_scene(tmp_path / "scene", sizes={("train", 1): 10})
    fails_with(capsys, "nerf-train", train, train_config(tmp_path, "experiment=fast_blender", "data.scene.downscale=1", f"data.root={root}"),
               "r_1.png is 10x10", "one size")


@pytest.mark.parametrize(
    ("meta", "expected"),
    [
        ({"fl_x": 10.0}, "missing or empty 'frames'"),
        ({"fl_x": 10.0, "frames": [{"file_path": "images/a.png"}]}, "frame 0: missing key 'transform_matrix'"),
        ({"frames": [{"file_path": "images/a.png", "transform_matrix": np.eye(4).tolist()}]}, "no focal length: expected 'fl_x'"),
        ({"fl_x": 10.0, "frames": [{"file_path": "images/a.png", "transform_matrix": [[1, 0, 0], [0, 1, 0]]}]}, "expected camera-to-world matrices of shape (N, 4, 4)"),
        ({"fl_x": 10.0, "frames": [{"file_path": "images/a.png", "transform_matrix": np.full((4, 4), np.nan).tolist()}]}, "non-finite"),
        ({"fl_x": 10.0, "frames": [{"file_path": "images/a.png", "transform_matrix": (2 * np.eye(4)).tolist()}]}, "last row"),
        ({"fl_x": 10.0, "frames": [{"file_path": "images/a.png", "transform_matrix": np.diag([2.0, 1.0, 1.0, 1.0]).tolist()}]}, "not rigid"),
        ({"fl_x": 10.0, "camera_model": "EQUIRECTANGULAR", "frames": [{"file_path": "images/a.png", "transform_matrix": np.eye(4).tolist()}]},
         "'camera_model' is 'EQUIRECTANGULAR': this loader reads"),
        ({"fl_x": 10.0, "camera_model": "OPENCV_FISHEYE", "k1": 0.1, "k2": 0.0, "k4": 0.0,
          "frames": [{"file_path": "images/a.png", "transform_matrix": np.eye(4).tolist()}]}, "OPENCV_FISHEYE needs k1, k2, k3, k4: 'k3' missing"),
    ],
    ids=["no_frames", "no_transform_matrix", "no_intrinsics", "not_4x4", "non_finite", "bad_last_row", "not_rigid", "unknown_camera_model",
         "fisheye_without_k3"],
)
def test_a_bad_transforms_json_names_the_file_and_key(tmp_path, capsys, meta, expected):
    root = tmp_path / "capture"
    write_png(root / "images" / "a.png", torch.full((8, 8, 3), 0.5))
    (root / "transforms.json").write_text(json.dumps(meta))
    fails_with(capsys, "nerf-train", train, train_config(tmp_path, "experiment=fast_unbounded", "data.scene.downscale=1", f"data.root={root}"),
               str(root / "transforms.json"), expected)


@pytest.mark.parametrize("problem", ["missing_key", "mismatched_counts"])
def test_a_bad_npz_names_the_key(tmp_path, capsys, problem):
    arrays = {"images_train": np.zeros((3, 4, 4, 3), np.uint8), "c2ws_train": np.tile(np.eye(4), (3, 1, 1)),
              "images_val": np.zeros((1, 4, 4, 3), np.uint8), "c2ws_val": np.tile(np.eye(4), (1, 1, 1)),
              "c2ws_test": np.tile(np.eye(4), (2, 1, 1)), "focal": np.array(5.0)}
    if problem == "missing_key":
        del arrays["c2ws_val"]
    else:
        arrays["c2ws_train"] = arrays["c2ws_train"][:2]
    np.savez(tmp_path / "scene.npz", **arrays)
    expected = "missing key(s) ['c2ws_val']" if problem == "missing_key" else "'images_train' has 3 images but 'c2ws_train' 2 cameras"
    fails_with(capsys, "nerf-train", train, train_config(tmp_path, "experiment=nerf_course", f"data.root={tmp_path / 'scene.npz'}"),
               str(tmp_path / "scene.npz"), expected)


def test_an_output_folder_that_cannot_be_written_is_named(tmp_path, capsys):
    blocked = tmp_path / "a_file"
    blocked.write_text("a file where the run folder should go")
    cfg = compose_config(["experiment=image", *QUIET, f"paths.output_dir={blocked / 'run'}"])
    fails_with(capsys, "nerf-train", train, cfg, str(blocked / "run"), "paths.output_dir=")


def test_a_nan_loss_stops_the_run_and_keeps_the_last_good_checkpoint(tmp_path, capsys):
    cfg = train_config(tmp_path, "experiment=image", "data.downscale=8", "data.batch_size=256", "trainer.max_steps=50", "data.val_steps=[]",
                       "data.val_every=null", "model.optimizer.lr=1e30", "callbacks.last_checkpoint.every_n_train_steps=1")
    line = fails_with(capsys, "nerf-train", train, cfg, "the training loss is", "last checkpoint keeps the last finite weights")
    step = int(line.split("step ")[1].split(":")[0])
    checkpoint = torch.load(tmp_path / "run" / "checkpoints" / "last.ckpt", weights_only=False)
    assert all(bool(torch.isfinite(value).all()) for value in checkpoint["state_dict"].values())
    assert 0 < checkpoint["global_step"] <= step  # written before the loss went bad, never after
    assert not (tmp_path / "run" / "metrics.json").exists()
    assert not list((tmp_path / "run" / "checkpoints").glob("*.tmp"))


def test_resuming_from_a_missing_checkpoint_is_named(tmp_path, capsys):
    fails_with(capsys, "nerf-train", train, train_config(tmp_path, "experiment=image", f"ckpt_path={tmp_path / 'gone.ckpt'}"),
               f"ckpt_path={tmp_path / 'gone.ckpt'} not found", "<run>/checkpoints/last.ckpt")


def run_command(*args: str, cwd) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", *args], cwd=cwd, capture_output=True, text=True, timeout=300)


def test_on_the_command_line_bad_input_is_one_line_and_exit_2(tmp_path):
    result = run_command("nerf_lightning.cli.train", "experiment=fast_blender", f"data.root={tmp_path / 'nowhere'}", f"hydra.run.dir={tmp_path / 'run'}",
                         *QUIET, cwd=tmp_path)
    assert result.returncode == 2
    assert result.stderr.strip().splitlines()[-1] == f"nerf-train: error: Blender scene folder not found: {tmp_path / 'nowhere'}"
    assert "Traceback" not in result.stderr


def test_an_unknown_group_option_lists_the_options(tmp_path):
    result = run_command("nerf_lightning.cli.train", "model=nerf_wrong", f"hydra.run.dir={tmp_path / 'run'}", cwd=ROOT)
    assert result.returncode != 0
    assert "Could not find 'model/nerf_wrong'" in result.stderr and "Available options in 'model'" in result.stderr and "ngp" in result.stderr
    assert "Traceback" not in result.stderr
