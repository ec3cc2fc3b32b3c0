"""Every command's own keys are checked where they enter (nerf_lightning/cli/keys.py): a wrong value stops the
command with exit status 2 and one line on stderr naming the key, the value and what it takes, before torch loads
and before the checkpoint or the input is looked for."""

from __future__ import annotations

import argparse
import os
import subprocess
import sys
from pathlib import Path

import pytest

from nerf_lightning.cli import keys
from nerf_lightning.config import compose_config
from nerf_lightning.errors import report_errors

BIN = Path(sys.executable).parent

# command -> (config name, the checker, what a command line gives besides the key tried)
COMMANDS = {
    "nerf-train": ("train", keys.check_train_keys, ["paths.output_dir=run"]),
    "nerf-render": ("render", keys.check_render_keys, ["ckpt_path=missing.ckpt"]),
    "nerf-eval": ("eval", keys.check_eval_keys, ["ckpt_path=missing.ckpt"]),
    "nerf-view": ("view", keys.check_view_keys, ["ckpt_path=missing.ckpt"]),
    "nerf-export": ("export", keys.check_export_keys, ["ckpt_path=missing.ckpt"]),
    "nerf-viz-cameras": ("viz", keys.check_viz_cameras_keys, []),
    "nerf-process-data": ("process_data", keys.check_process_data_keys, ["input=photos", "output=capture"]),
}

# (command, override, words the one line must hold: the key, the value given, the values it takes)
WRONG = [
    ("nerf-train", "seed=abc", ["seed must be an integer", "'abc'"]),
    ("nerf-train", "seed=-1", ["seed must be an integer from 0", "got -1"]),
    ("nerf-train", "seed=1.5", ["seed must be an integer", "got 1.5"]),
    ("nerf-train", "name=''", ["name must be a run name", "got ''"]),
    ("nerf-train", "ckpt_path=[1,2]", ["ckpt_path must be a checkpoint", "or null", "got [1, 2]"]),
    ("nerf-render", "device=gpu", ["device must be auto, cpu, cuda, cuda:<index> or mps", "got 'gpu'"]),
    ("nerf-render", "device=cuda:x", ["device must be", "got 'cuda:x'"]),
    ("nerf-render", "render.scale=0", ["render.scale must be a number > 0", "got 0"]),
    ("nerf-render", "render.scale=abc", ["render.scale must be a number > 0", "got 'abc'"]),
    ("nerf-render", "render.path=circle", ["render.path must be test, orbit, spiral or a camera path file (.json)", "got 'circle'"]),
    ("nerf-render", "render.path=360", ["render.path must be test, orbit, spiral or a camera path file (.json)", "got 360"]),
    ("nerf-render", "render.dataparser_transforms=[1]", ["render.dataparser_transforms must be nerfstudio's dataparser_transforms.json", "got [1]"]),
    ("nerf-eval", "eval.lpips=sometimes", ["eval.lpips must be auto, download or off", "got 'sometimes'"]),
    ("nerf-render", "render.frames=0", ["render.frames must be an integer >= 2", "got 0"]),
    ("nerf-render", "render.frames=1", ["render.frames must be an integer >= 2", "got 1"]),
    ("nerf-render", "render.frames=2.5", ["render.frames must be an integer >= 2", "got 2.5"]),
    ("nerf-render", "render.fps=0", ["render.fps must be a number > 0", "got 0"]),
    ("nerf-render", "render.fps=inf", ["render.fps must be a number > 0", "got inf"]),
    ("nerf-render", "render.depth_colormap=rainbowz", ["render.depth_colormap must be grey or a matplotlib colormap", "got 'rainbowz'"]),
    ("nerf-eval", "split=nonsense", ["split must be test or val, got 'nonsense'"]),
    ("nerf-eval", "split=train", ["split must be test or val, got 'train'"]),
    ("nerf-eval", "max_views=0", ["max_views must be an integer >= 1 or null", "got 0"]),
    ("nerf-eval", "max_views=all", ["max_views must be an integer >= 1 or null", "got 'all'"]),
    ("nerf-eval", "device=tpu", ["device must be", "got 'tpu'"]),
    ("nerf-eval", "root=[a]", ["root must be a transforms.json", "got ['a']"]),
    ("nerf-view", "port=0", ["port must be a TCP port, an integer from 1 to 65535", "got 0"]),
    ("nerf-view", "port=65536", ["port must be a TCP port", "got 65536"]),
    ("nerf-view", "port=http", ["port must be a TCP port", "got 'http'"]),
    ("nerf-view", "host=''", ["host must be an address", "got ''"]),
    ("nerf-view", "view.moving_frame_s=0", ["view.moving_frame_s must be a number > 0", "got 0"]),
    ("nerf-view", "view.max_resolution=4", ["view.max_resolution must be an integer >= 8", "got 4"]),
    ("nerf-view", "device=cuda0", ["device must be", "got 'cuda0'"]),
    ("nerf-export", "format=stl", ["format must be ply, obj, glb or spz", "got 'stl'"]),
    ("nerf-render", "trust_checkpoint=maybe", ["trust_checkpoint must be true or false", "got 'maybe'"]),
    ("nerf-eval", "trust_checkpoint=1", ["trust_checkpoint must be true or false", "got 1"]),
    ("nerf-export", "resolution=1", ["resolution must be an integer >= 2", "got 1"]),
    ("nerf-export", "resolution=high", ["resolution must be an integer >= 2", "got 'high'"]),
    ("nerf-export", "threshold=high", ["threshold must be a number", "got 'high'"]),
    ("nerf-export", "keep=biggest", ["keep must be largest, all or a number of faces (>= 1)", "got 'biggest'"]),
    ("nerf-export", "keep=0", ["keep must be largest, all or a number of faces (>= 1)", "got 0"]),
    ("nerf-export", "frame=world", ["frame must be capture or scene", "got 'world'"]),
    ("nerf-export", "bounds=[[0,0,0],[1,1]]", ["bounds must be null or [[x, y, z], [x, y, z]]", "got [[0, 0, 0], [1, 1]]"]),
    ("nerf-export", "bounds=[[0,0,0],[1,-1,1]]", ["bounds must be null", "low < high", "got [[0, 0, 0], [1, -1, 1]]"]),
    ("nerf-export", "bounds=2", ["bounds must be null", "got 2"]),
    ("nerf-export", "device=gpu", ["device must be", "got 'gpu'"]),
    ("nerf-export", "sh1_bits=9", ["sh1_bits must be an integer from 1 to 8", "got 9"]),
    ("nerf-export", "sh_rest_bits=0", ["sh_rest_bits must be an integer from 1 to 8", "got 0"]),
    ("nerf-viz-cameras", "viz.backend=plotly", ["viz.backend must be png or viser", "got 'plotly'"]),
    ("nerf-viz-cameras", "viz.n_rays=0", ["viz.n_rays must be an integer >= 1", "got 0"]),
    ("nerf-viz-cameras", "viz.n_rays_one_camera=-3", ["viz.n_rays_one_camera must be an integer >= 1", "got -3"]),
    ("nerf-viz-cameras", "viz.n_samples=0", ["viz.n_samples must be an integer >= 1", "got 0"]),
    ("nerf-viz-cameras", "viz.camera=-1", ["viz.camera must be an integer >= 0", "got -1"]),
    ("nerf-viz-cameras", "viz.port=99999", ["viz.port must be a TCP port", "got 99999"]),
    ("nerf-viz-cameras", "viz.host=''", ["viz.host must be an address", "got ''"]),
    ("nerf-viz-cameras", "seed=x", ["seed must be an integer", "got 'x'"]),
    ("nerf-viz-cameras", "device=gpu", ["device must be", "got 'gpu'"]),
    ("nerf-process-data", "frames=0", ["frames must be an integer >= 1", "got 0"]),
    ("nerf-process-data", "matcher=vocab", ["matcher must be auto, exhaustive or sequential", "got 'vocab'"]),
    ("nerf-process-data", "mapper=hierarchical", ["mapper must be auto, global or incremental", "got 'hierarchical'"]),
    ("nerf-process-data", "camera_model=FISHEYE", ["camera_model must be SIMPLE_PINHOLE, PINHOLE, SIMPLE_RADIAL, RADIAL, OPENCV or OPENCV_FISHEYE", "got 'FISHEYE'"]),
    ("nerf-process-data", "single_camera=yes", ["single_camera must be true or false", "got 'yes'"]),
    ("nerf-process-data", "max_size=32", ["max_size must be an integer >= 64", "got 32"]),
    ("nerf-process-data", "max_features=0", ["max_features must be an integer >= 1", "got 0"]),
    ("nerf-process-data", "downscales=[1,2]", ["downscales must be a list of integers of 2 or more", "got [1, 2]"]),
    ("nerf-process-data", "downscales=4", ["downscales must be a list of integers of 2 or more", "got 4"]),
    ("nerf-process-data", "min_registered=1.5", ["min_registered must be a number >= 0 and <= 1", "got 1.5"]),
    ("nerf-process-data", "seed=-2", ["seed must be an integer", "got -2"]),
    ("nerf-process-data", "progress=maybe", ["progress must be true or false", "got 'maybe'"]),
    ("nerf-process-data", "verbose=1", ["verbose must be true or false", "got 1"]),
]


def checked(command: str, *overrides: str):
    """The command's config with ``overrides`` and its checker."""
    config_name, check, given = COMMANDS[command]
    return compose_config([*given, *overrides], config_name=config_name), check


def fails_with(capsys, command: str, task, cfg, words) -> str:
    """``task(cfg)`` run as the command runs it exits 2 with one stderr line holding every one of ``words``."""
    with pytest.raises(SystemExit) as stopped:
        report_errors(command)(task)(cfg)
    assert stopped.value.code == 2
    lines = capsys.readouterr().err.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith(f"{command}: error: "), lines
    for word in words:
        assert word in lines[0], (word, lines[0])
    return lines[0]


@pytest.mark.parametrize(("command", "override", "words"), WRONG, ids=[f"{c}:{o}" for c, o, _ in WRONG])
def test_a_wrong_value_is_one_line_naming_the_key_and_exit_2(capsys, command, override, words):
    cfg, check = checked(command, override)
    fails_with(capsys, command, check, cfg, words)


@pytest.mark.parametrize("command", sorted(COMMANDS))
def test_the_shipped_defaults_pass(command):
    cfg, check = checked(command)
    check(cfg)


@pytest.mark.parametrize(("command", "overrides"), [
    ("nerf-train", ["name=2024", "seed=4294967295", "ckpt_path=", "experiment=nerfacto_360_cpu"]),
    ("nerf-train", ["ckpt_path=outputs/x/checkpoints/last.ckpt"]),
    ("nerf-render", ["device=cpu", "render.scale=0.5", "render.path=spiral", "render.frames=2", "render.fps=12.5", "render.depth_colormap=turbo"]),
    ("nerf-render", ["device=cuda:1", "render.path=test", "render.scale=2"]),
    ("nerf-render", ["device=CUDA", "render.depth_colormap=grey"]),
    ("nerf-render", ["device=mps"]),
    ("nerf-eval", ["split=val", "max_views=3", "root=other/transforms.json", "device=null"]),
    ("nerf-eval", ["split=test", "max_views=null", "root=null"]),
    ("nerf-view", ["port=1", "host=0.0.0.0", "view.moving_frame_s=0.05", "view.max_resolution=8"]),
    ("nerf-view", ["port=65535"]),
    ("nerf-export", ["format=glb", "resolution=2", "threshold=5", "keep=largest", "frame=scene", "bounds=[[-1,-1,-1],[1,1.5,1]]"]),
    ("nerf-export", ["format=obj", "threshold=-0.5", "keep=all"]),
    ("nerf-export", ["keep='12'"]),
    ("nerf-export", ["format=spz", "sh1_bits=8", "sh_rest_bits=1"]),
    ("nerf-viz-cameras", ["viz.backend=viser", "viz.camera=3", "viz.port=9000", "device=cpu"]),
    ("nerf-process-data", ["frames=300", "matcher=sequential", "mapper=global", "camera_model=PINHOLE", "single_camera=false",
                           "downscales=[]", "min_registered=0", "max_size=64"]),
    ("nerf-process-data", ["downscales=[2]", "min_registered=1"]),
], ids=lambda value: value if isinstance(value, str) else " ".join(value))
def test_right_values_pass(command, overrides):
    cfg, check = checked(command, *overrides)
    check(cfg)


def test_a_mandatory_key_not_given_is_named():
    cfg = compose_config(["output=capture"], config_name="process_data")
    with pytest.raises(ValueError, match=r"^input must be given: a folder of photos or a video file"):
        keys.check_process_data_keys(cfg)


@pytest.mark.parametrize(("options", "words"), [
    ({"views": 5, "size": 100}, ["--views must be an integer >= 10", "got 5"]),
    ({"views": 10, "size": 0}, ["--size must be an integer >= 1", "got 0"]),
])
def test_make_scene_options(options, words):
    with pytest.raises(ValueError) as refused:
        keys.check_make_scene_keys(argparse.Namespace(directory="scene", **options))
    assert all(word in str(refused.value) for word in words), str(refused.value)
    keys.check_make_scene_keys(argparse.Namespace(directory="scene", views=10, size=1))


@pytest.fixture
def without_torch(tmp_path):
    """An environment in which importing torch ends the process with status 99: what runs in it never loaded torch."""
    poisoned = tmp_path / "no_torch"
    (poisoned / "torch").mkdir(parents=True)
    (poisoned / "torch" / "__init__.py").write_text("import os\nos.write(2, b'torch was imported\\n')\nos._exit(99)\n")
    return dict(os.environ, PYTHONPATH=os.pathsep.join(filter(None, [str(poisoned), os.environ.get("PYTHONPATH")])))


# every command with a wrong key, and the one line it must print: the check comes first, before torch loads and before
# the checkpoint (x), the input or the port is looked at (device=gpu with port=0: the device is named, not the port)
@pytest.mark.parametrize(("command", "args", "words"), [
    ("nerf-train", ["seed=abc", "hydra.run.dir=run"], "seed must be an integer from 0 to 4294967295, got 'abc'"),
    ("nerf-render", ["ckpt_path=x", "render.frames=0"], "render.frames must be an integer >= 2, got 0"),
    ("nerf-eval", ["ckpt_path=x", "split=nonsense"], "split must be test or val, got 'nonsense'"),
    ("nerf-view", ["ckpt_path=x", "device=gpu", "port=0"], "device must be auto, cpu, cuda, cuda:<index> or mps, got 'gpu'"),
    ("nerf-export", ["ckpt_path=x", "format=stl"], "format must be ply, obj, glb or spz, got 'stl'"),
    ("nerf-viz-cameras", ["viz.n_samples=0"], "viz.n_samples must be an integer >= 1, got 0"),
    ("nerf-process-data", ["input=photos", "output=capture", "matcher=vocab"], "matcher must be auto, exhaustive or sequential, got 'vocab'"),
    ("nerf-process-data", ["output=capture", "progress=false"], "input must be given: a folder of photos or a video file, e.g. input=..."),
    ("nerf-make-scene", ["scene", "--views", "3"], "--views must be an integer >= 10, got 3"),
])
def test_the_installed_commands(tmp_path, without_torch, command, args, words):
    """As a user runs them: exit 2, one line naming the key, nothing about the checkpoint (x) that is not there, and
    torch never imported (the environment's torch ends the process with status 99)."""
    result = subprocess.run([str(BIN / command), *args], cwd=tmp_path, env=without_torch, capture_output=True, text=True, timeout=300)
    assert result.returncode == 2, (result.returncode, result.stdout[-2000:], result.stderr[-2000:])
    assert result.stderr.strip().splitlines() == [f"{command}: error: {words}"], result.stderr[-2000:]
    assert not (tmp_path / "scene").exists()


def test_the_checks_take_what_the_library_takes():
    """The keys' names come from their owners (no copies); what the checks let through is what the library accepts."""
    import torch

    from nerf_lightning.outputs.export import EXPORT_FORMATS as WRITERS
    from nerf_lightning.outputs.mesh import parse_keep

    assert set(keys.EXPORT_FORMATS) == set(WRITERS)  # every format the check lets through has a writer
    for keep in ("largest", "all", "ALL", 1, 100, "100", 0, -1, "biggest", 1.5, True, None):
        try:
            parse_keep(keep)
        except ValueError:
            accepted = False
        else:
            accepted = True
        assert accepted == (not _refused(keys.check_keep, {"keep": keep})), keep
    for device in ("cpu", "cuda", "cuda:1", "mps", "auto", "gpu", "tpu", "cuda:x", "cuda0", "xla"):
        form = not _refused(keys.check_device, {"device": device})
        try:
            torch.device(device)
        except (RuntimeError, ValueError):
            known = device == "auto"
        else:
            known = torch.device(device).type in ("cpu", "cuda", "mps")
        assert form == known, device


def _refused(check, cfg) -> bool:
    try:
        check(cfg)
    except ValueError:
        return True
    return False


def test_an_llff_capture_loads_as_360_from_the_command_line_value(procedural_scene, tmp_path):
    """The README's `nerf-train experiment=nerfacto_360_cpu data/scene=llff data.root=... data.scene.layout=360`: Hydra reads
    360 as a number, which the loader takes as the name."""
    from hydra.utils import instantiate

    from tests.data.test_llff import write_llff

    root = write_llff(procedural_scene.train.subset(list(range(0, 80, 4))), tmp_path / "capture")
    cfg = compose_config(["experiment=nerfacto_360_cpu", "data/scene=llff", f"data.root={root}", "data.scene.layout=360",
                          "data.scene.downscale=2", "data.scene.holdout_every=5", f"paths.output_dir={tmp_path / 'run'}"])
    assert cfg.data.scene.layout == 360
    keys.check_train_keys(cfg)
    datamodule = instantiate(cfg.data)
    datamodule.setup()
    scene = datamodule.scene
    assert scene.near == 0.05 and "spiral" not in scene.splits  # the 360 layout: normalised, no forward spiral
    assert float(scene.train.c2w[:, :3, 3].abs().max()) <= 1.0 + 1e-5
    with pytest.raises(ValueError, match="data.scene.layout must be one of .* got '180'"):
        instantiate(compose_config(["data=rays", "data/scene=llff", f"data.root={root}", "data.scene.layout=180", f"paths.output_dir={tmp_path / 'run'}"]).data).setup()
