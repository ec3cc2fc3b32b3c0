"""Every command's own keys checked where they enter: ``check_<command>_keys(cfg)`` is the first line of the command's
task, before torch loads, and raises one ``ValueError`` line that names the key, the value given and the values it
takes (``split must be test or val, got 'nonsense'``), which :func:`~nerf_lightning.errors.report_errors` prints as
``nerf-<command>: error: ...`` with exit status 2.

Only the commands' top-level keys are checked here: the keys of the objects a config builds (``model.*``, ``data.*``,
``trainer.*``, ``callbacks.*``) are checked by those objects, and what needs the file system or the machine (a path
that exists, a port that is free, a CUDA device that is there) where it is used. Nothing here imports torch: the
names a key takes come from their owners' torch-free modules (``data/choices.py``, ``capture/choices.py``,
``outputs/choices.py``, ``devices.py``), which the modules that act on them read too.

Hydra's parser reads ``360`` as the integer 360 and ``1e3`` as a float: a key that takes names compares ``str(value)``,
and a key that takes an integer refuses a float.
"""

from __future__ import annotations

import argparse
import math
import re
from collections.abc import Sequence
from typing import Any

from omegaconf import DictConfig, ListConfig, OmegaConf

from nerf_lightning.capture.choices import CAMERA_MODELS, MAPPERS, MASK_OBJECTS, MATCHERS
from nerf_lightning.data.choices import PROCEDURAL_MIN_VIEWS, RENDER_PATHS, is_camera_path_file
from nerf_lightning.devices import DEVICE_CHOICES
from nerf_lightning.outputs.choices import EXPORT_FORMATS, LPIPS_MODES, MESH_FRAMES

# a device's form; whether the machine has it is checked by devices.resolve_device when the command picks it
DEVICE_FORM = re.compile(r"auto|cpu(:0)?|cuda(:\d+)?|mps(:0)?")
SPLITS = ("test", "val")
VIZ_BACKENDS = ("png", "viser")
SEED_RANGE = (0, 2**32 - 1)  # what Lightning's seed_everything and numpy take


def shown(value: Any) -> str:
    """A value as the messages quote it: strings in quotes, numbers, lists and null as written."""
    if isinstance(value, (DictConfig, ListConfig)):
        value = OmegaConf.to_container(value, resolve=False)
    if value is None:
        return "null"
    if isinstance(value, bool):
        return str(value).lower()
    return f"'{value}'" if isinstance(value, str) else str(value)


def either(names: Sequence[str]) -> str:
    """``a or b``, ``a, b or c``."""
    return " or ".join(names) if len(names) < 3 else f"{', '.join(names[:-1])} or {names[-1]}"


def value_of(cfg: DictConfig | argparse.Namespace | dict, key: str) -> Any:
    """The value of a dotted ``key`` (None when it is absent, null or ???)."""
    if isinstance(cfg, DictConfig):
        return OmegaConf.select(cfg, key, default=None)
    value = vars(cfg) if isinstance(cfg, argparse.Namespace) else cfg
    for part in key.split("."):
        value = value.get(part) if isinstance(value, dict) else None
    return value


def is_integer(value: Any) -> bool:
    return isinstance(value, int) and not isinstance(value, bool)


def is_number(value: Any) -> bool:
    return isinstance(value, (int, float)) and not isinstance(value, bool) and math.isfinite(value)


def check_choice(cfg, key: str, choices: Sequence[str]) -> None:
    """A name among ``choices`` (compared as ``str``: Hydra reads 360 as a number)."""
    value = value_of(cfg, key)
    if value is None or str(value) not in choices:
        raise ValueError(f"{key} must be {either(choices)}, got {shown(value)}")


def check_integer(cfg, key: str, low: int, high: int | None = None, null: bool = False, name: str | None = None) -> None:
    """An integer in [low, high] (high None: no limit), or null where ``null``."""
    value = value_of(cfg, key)
    if value is None and null:
        return
    if not is_integer(value) or value < low or (high is not None and value > high):
        bounds = f">= {low}" if high is None else f"from {low} to {high}"
        raise ValueError(f"{name or key} must be {'a TCP port, ' if key.endswith('port') else ''}an integer {bounds}"
                         f"{' or null' if null else ''}, got {shown(value)}")


def check_number(cfg, key: str, above: float | None = None, low: float | None = None, high: float | None = None,
                 below: float | None = None, null: bool = False) -> None:
    """A finite number (int or float) > ``above``, >= ``low``, <= ``high``, < ``below`` where given."""
    value = value_of(cfg, key)
    if value is None and null:
        return
    limits = [f"> {above:g}" if above is not None else "", f">= {low:g}" if low is not None else "",
              f"<= {high:g}" if high is not None else "", f"< {below:g}" if below is not None else ""]
    wrong = (not is_number(value) or (above is not None and value <= above) or (low is not None and value < low)
             or (high is not None and value > high) or (below is not None and value >= below))
    if wrong:
        condition = " and ".join(limit for limit in limits if limit)
        raise ValueError(f"{key} must be a number{' ' + condition if condition else ''}{' or null' if null else ''}, got {shown(value)}")


def check_bool(cfg, key: str) -> None:
    value = value_of(cfg, key)
    if not isinstance(value, bool):
        raise ValueError(f"{key} must be true or false, got {shown(value)}")


def check_text(cfg, key: str, what: str, null: bool = False) -> None:
    """A non-empty name or path (numbers read as such by Hydra count: ``name=2024`` names a run); where ``null``,
    also null or empty (``ckpt_path=``), which the commands read as none."""
    value = value_of(cfg, key)
    if null and (value is None or value == ""):
        return
    if value is None or isinstance(value, (bool, DictConfig, ListConfig, dict, list)) or not str(value).strip():
        raise ValueError(f"{key} must be {what}{' or null' if null else ''}, got {shown(value)}")


def check_given(cfg: DictConfig, key: str, what: str) -> None:
    """A mandatory key (``???`` in the config) given on the command line."""
    if OmegaConf.is_missing(cfg, key):
        raise ValueError(f"{key} must be given: {what}, e.g. {key}=...")
    check_text(cfg, key, what)


def check_device(cfg) -> None:
    """``device``: auto, cpu, cuda, cuda:<index> or mps; :func:`nerf_lightning.devices.resolve_device` checks that the
    machine has it when the command picks it."""
    value = value_of(cfg, "device")
    if value is None:  # null is auto, as resolve_device takes it
        return
    if not DEVICE_FORM.fullmatch(str(value).strip().lower()):
        raise ValueError(f"device must be {DEVICE_CHOICES}, got {shown(value)}")


def check_colormap(cfg, key: str) -> None:
    """grey, or a matplotlib colormap (matplotlib, not torch, is imported to know them)."""
    value = value_of(cfg, key)
    if value == "grey":
        return
    import matplotlib

    if value is None or str(value) not in matplotlib.colormaps:
        raise ValueError(f"{key} must be grey or a matplotlib colormap (turbo, viridis, ...), got {shown(value)}")


def check_keep(cfg) -> None:
    """export ``keep``: largest, all, or a number of faces (>= 1), as :func:`nerf_lightning.outputs.mesh.parse_keep`
    reads it."""
    value = value_of(cfg, "keep")
    text = "" if value is None or isinstance(value, bool) else str(value).strip().lower()
    if not (text in ("largest", "all") or (text.isdigit() and int(text) >= 1)):
        raise ValueError(f"keep must be largest, all or a number of faces (>= 1), got {shown(value)}")


def check_bounds(cfg) -> None:
    """export ``bounds``: null, or [[x, y, z] low, [x, y, z] high] with low < high on every axis."""
    value = value_of(cfg, "bounds")
    if value is None:
        return
    corners = OmegaConf.to_container(value) if isinstance(value, ListConfig) else value
    if (not isinstance(corners, list) or len(corners) != 2 or any(not isinstance(c, list) or len(c) != 3 for c in corners)
            or not all(is_number(x) for c in corners for x in c) or any(a >= b for a, b in zip(*corners))):
        raise ValueError(f"bounds must be null or [[x, y, z], [x, y, z]], the box's low and high corners with low < high on "
                         f"every axis, got {shown(value)}")


def check_port(cfg, key: str) -> None:
    check_integer(cfg, key, 1, 65535)


# ---- the commands


def check_train_keys(cfg: DictConfig) -> None:
    """nerf-train's own top-level keys (the model, data, trainer and callbacks, the live viewer among them, check
    theirs when built; whether ``ckpt_path`` exists is checked by the training before it loads anything)."""
    check_bool(cfg, "trust_checkpoint")
    check_text(cfg, "name", "a run name (the run folder is outputs/<name>/<time>)")
    check_integer(cfg, "seed", *SEED_RANGE)
    check_text(cfg, "ckpt_path", "a checkpoint to resume from, such as <run>/checkpoints/last.ckpt", null=True)


def check_render_keys(cfg: DictConfig) -> None:
    check_bool(cfg, "trust_checkpoint")
    check_device(cfg)
    check_number(cfg, "render.scale", above=0.0)
    if not is_camera_path_file(value_of(cfg, "render.path")):
        check_choice(cfg, "render.path", (*RENDER_PATHS, "a camera path file (.json)"))
    check_text(cfg, "render.dataparser_transforms", "nerfstudio's dataparser_transforms.json", null=True)
    check_integer(cfg, "render.frames", 2)
    check_number(cfg, "render.fps", above=0.0)
    check_colormap(cfg, "render.depth_colormap")


def check_eval_keys(cfg: DictConfig) -> None:
    check_bool(cfg, "trust_checkpoint")
    check_device(cfg)
    check_choice(cfg, "split", SPLITS)
    check_text(cfg, "root", "a transforms.json (or its folder) of the same capture", null=True)
    check_integer(cfg, "max_views", 1, null=True)
    check_choice(cfg, "eval.lpips", LPIPS_MODES)
    check_text(cfg, "eval.lpips_weights", "a file of AlexNet's and LPIPS's weights", null=True)


def check_view_keys(cfg: DictConfig) -> None:
    check_bool(cfg, "trust_checkpoint")
    check_device(cfg)
    check_text(cfg, "host", "an address to serve the page on, such as 127.0.0.1 or 0.0.0.0")
    check_port(cfg, "port")
    check_number(cfg, "view.moving_frame_s", above=0.0)
    check_integer(cfg, "view.max_resolution", 8)


def check_export_keys(cfg: DictConfig) -> None:
    check_bool(cfg, "trust_checkpoint")
    check_device(cfg)
    check_bounds(cfg)
    check_choice(cfg, "frame", MESH_FRAMES)
    check_integer(cfg, "resolution", 2)
    check_number(cfg, "threshold")
    check_choice(cfg, "format", EXPORT_FORMATS)
    check_keep(cfg)
    check_integer(cfg, "sh1_bits", 1, 8)
    check_integer(cfg, "sh_rest_bits", 1, 8)


def check_viz_cameras_keys(cfg: DictConfig) -> None:
    """nerf-viz-cameras's own keys (``data.*`` is checked by the data module; ``viz.camera`` against the scene's
    training views once it is loaded)."""
    check_integer(cfg, "seed", *SEED_RANGE)
    check_device(cfg)
    check_choice(cfg, "viz.backend", VIZ_BACKENDS)
    check_integer(cfg, "viz.n_rays", 1)
    check_integer(cfg, "viz.n_rays_one_camera", 1)
    check_integer(cfg, "viz.n_samples", 1)
    check_integer(cfg, "viz.camera", 0)
    check_text(cfg, "viz.host", "an address to serve the view on, such as 127.0.0.1 or 0.0.0.0")
    check_port(cfg, "viz.port")


def check_process_data_keys(cfg: DictConfig) -> None:
    """nerf-process-data's keys (whether ``input`` exists and is photos or a video, and ``masks`` a folder of masks, is
    checked as it is read)."""
    check_given(cfg, "input", "a folder of photos or a video file")
    check_given(cfg, "output", "the folder to write the capture into")
    check_integer(cfg, "frames", 1)
    check_choice(cfg, "matcher", MATCHERS)
    check_choice(cfg, "mapper", MAPPERS)
    check_choice(cfg, "camera_model", CAMERA_MODELS)
    check_bool(cfg, "single_camera")
    check_integer(cfg, "max_size", 64)
    check_integer(cfg, "max_features", 1)
    downscales = value_of(cfg, "downscales")
    if not isinstance(downscales, (list, ListConfig)) or not all(is_integer(factor) and factor >= 2 for factor in downscales):
        raise ValueError(f"downscales must be a list of integers of 2 or more, such as [2, 4, 8] (or []), got {shown(downscales)}")
    check_number(cfg, "min_registered", low=0.0, high=1.0)
    check_bool(cfg, "escalate")
    check_integer(cfg, "seed", *SEED_RANGE)
    check_text(cfg, "masks", "a folder with a mask for each photo", null=True)
    check_choice(cfg, "mask_object", MASK_OBJECTS)
    check_number(cfg, "min_mask_agreement", low=0.0, high=1.0)
    check_bool(cfg, "progress")
    check_bool(cfg, "verbose")


def check_make_scene_keys(args: argparse.Namespace) -> None:
    """nerf-make-scene's options (argparse has made them integers)."""
    check_integer(args, "views", PROCEDURAL_MIN_VIEWS, name="--views")
    check_integer(args, "size", 1, name="--size")
