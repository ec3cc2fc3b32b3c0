"""Composing the shipped Hydra configs from Python (tests, benchmarks, notebooks)."""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path
from typing import Any

from hydra import compose, initialize_config_module
from omegaconf import DictConfig, OmegaConf


def compose_config(overrides: Sequence[str] = (), config_name: str = "train") -> DictConfig:
    """The config ``nerf-train`` would run with these overrides. Set ``paths.output_dir`` among them:
    outside a Hydra run there is no run folder to default to."""
    with initialize_config_module(config_module="nerf_lightning.conf", version_base="1.3"):
        return compose(config_name=config_name, overrides=list(overrides))


def run_dir_of(ckpt_path: str | Path) -> Path:
    """The run folder of a checkpoint: <run> for <run>/checkpoints/x.ckpt, else the checkpoint's folder."""
    folder = Path(ckpt_path).expanduser().resolve().parent
    return folder.parent if folder.name == "checkpoints" else folder


# `${run_dir_of:${ckpt_path}}` in render.yaml, eval.yaml, export.yaml and view.yaml: outputs go beside the run. Here,
# where the commands find it before they load torch.
OmegaConf.register_new_resolver("run_dir_of", lambda path: str(run_dir_of(path)), replace=True)


# Why keys moved, by release (see CHANGELOG.md)
OBJECTS_02 = "in nerf-lightning 0.2, when samplers and the scene space became objects"
VIEWER_03 = "in nerf-lightning 0.3, when the live viewer became a callback"
MODES_04 = "after nerf-lightning 0.3, when the renderer's two modes became two renderers"
DATA_04 = "in nerf-lightning 0.4, when data= came to name the DataModule (rays, views, pixels), data/scene= the format"

# data= choices that went: the old choice -> what to write now
RENAMED_DATA = {**{name: f"data=rays data/scene={name} (data=views data/scene={name} for model=splat)"
                   for name in ("blender", "llff", "npz", "procedural", "transforms", "turntable")},
                "image": "data=pixels"}
START_04 = "in nerf-lightning 0.4, when the splats' start and loss became objects (model/start, model.loss)"
RASTERIZER_04 = "in nerf-lightning 0.4, when what draws a splat model's views became one object, model/rasterizer"
MARCH_04 = "in nerf-lightning 0.4, when the fixed-shape march became a sampler"

# Keys that moved: old key -> (the key now, a note, why), where the rest of a longer old key carries over to the new one
RENAMED_KEYS = {
    "model.fine_field": ("model.sampler.coarse_field", "with model/sampler=hierarchical", OBJECTS_02),
    "model.n_samples": ("model.sampler.n_samples", "", OBJECTS_02),
    "model.n_fine_samples": ("model.sampler.n_fine_samples", "with model/sampler=hierarchical", OBJECTS_02),
    "model.occupancy_grid": ("model.sampler.grid", "with model/sampler=occupancy_grid", OBJECTS_02),
    "model.render_step_size": ("model.sampler.step_size", "", OBJECTS_02),
    "model.cone_angle": ("model.sampler.cone_angle", "", OBJECTS_02),
    "model.alpha_threshold": ("model.sampler.alpha_threshold", "", OBJECTS_02),
    "model.early_stop_eps": ("model.renderer.early_stop_eps", "", OBJECTS_02),
    "model.samples_per_round": ("model.renderer.samples_per_round", "", OBJECTS_02),
    "model.field.contracted": ("data.contract", "with model.field.aabb=[-2,-2,-2,2,2,2], the contraction's cube", OBJECTS_02),
    **{f"model.field.{key}": (f"model.field.encoding.{key}", "", OBJECTS_02)
       for key in ("n_levels", "features_per_level", "log2_table_size", "base_resolution", "max_resolution")},
    **{f"viewer_{key}": (f"callbacks.viewer.{key}", "with viewer=live", VIEWER_03) for key in ("host", "port", "time_share")},
    "model.random_count": ("model.start.random.count", "", START_04),
    "model.random_start": ("model/start/random=box or model/start/random=views", "", START_04),
    "model.random_near": ("model.start.random.near", "with model/start/random=views", START_04),
    "model.random_extent": ("model.start.random.extent", "with model/start/random=views: model.start.random.far", START_04),
    "model.random_scale": ("model.start.random.scale", "", START_04),
    "model.triangulate": ("model/start=triangulated", "model/start=points for false", START_04),
    "model.random_beside_points": ("model.start.beside", "", START_04),
    "model.ssim_weight": ("model.loss.ssim_weight", "", START_04),
    "model.sh_degree_interval": ("model.gaussians.sh_degree_interval", "", START_04),
    "model.max_pairs": ("model.rasterizer.max_pairs", "", RASTERIZER_04),
    "model.antialiased": ("model.rasterizer.antialiased", "", RASTERIZER_04),
    "model.sampler.capacity": ("model.sampler.samples_per_step", "with model/sampler=fixed_shape_grid", MARCH_04),
    "model.sampler.march_capacity": ("model.sampler.density_pass_samples", "with model/sampler=fixed_shape_grid", MARCH_04),
}

# Keys that moved for the splats alone (the radiance fields keep them where they were): answered where the command
# line chooses the splats (model=splat, or an experiment=splat_* preset)
SPLAT_RENAMED_KEYS = {key: (f"model.loss.{key[len('model.'):]}", "", START_04) for key in ("model.mask_loss", "model.train_background")}


def renamed_key_message(overrides: Sequence[str]) -> str | None:
    """The first command-line override that uses a key that moved, as a sentence saying what to write instead; or None."""
    for override in overrides:
        key, _, value = override.partition("=")
        key = key.lstrip("+~").split("@", 1)[0]
        if key == "viewer" and value.strip().lower() in ("true", "false", "yes", "no", "on", "off", "1", "0"):
            # Hydra takes a config group's choice as a name, and true is not one
            return (f"'viewer={value}' was replaced {VIEWER_03} (see CHANGELOG.md): use viewer=live for the live view, "
                    "or leave viewer out for none")
        if key == "model.renderer.fixed_shapes":
            return (f"'{key}' was replaced {MODES_04} (see CHANGELOG.md): for a step of fixed shapes use "
                    "model/sampler=fixed_shape_grid (an occupancy grid) or model/renderer=table (the proposal sampler), "
                    "model/renderer=rounds for rounds")
        if key == "model/renderer" and value.strip() == "volume":
            return (f"'model/renderer=volume' was replaced {MODES_04} (see CHANGELOG.md): use model/renderer=rounds "
                    "(its keys are the same), or model/renderer=table for a step of fixed shapes (the proposal sampler)")
        if key == "data" and value.strip() in RENAMED_DATA:
            return f"'data={value.strip()}' was replaced {DATA_04} (see CHANGELOG.md): use {RENAMED_DATA[value.strip()]}"
        if key == "model.rasterizer" and value.strip() in ("auto", "tiles", "pairs"):
            # the name of a group's choice, where a value was written before (model.rasterizer.* are its keys now)
            return f"'{override}' was replaced {RASTERIZER_04} (see CHANGELOG.md): use model/rasterizer={value.strip()}"
        for old, (new, note, why) in RENAMED_KEYS.items():
            if key == old or key.startswith(old + "."):
                now = new + key[len(old):] + (f" ({note})" if note else "")
                return f"'{key}' was moved {why} (see CHANGELOG.md): use {now}"
    return splat_key_message(overrides)


def splat_key_message(overrides: Sequence[str]) -> str | None:
    """:func:`renamed_key_message` for the keys of :data:`SPLAT_RENAMED_KEYS`, where the overrides choose the splats."""
    if not any(override.startswith(("model=splat", "experiment=splat_")) for override in overrides):
        return None
    keys = [override.partition("=")[0].lstrip("+~").split("@", 1)[0] for override in overrides]
    for key in keys:
        if key in SPLAT_RENAMED_KEYS:
            new, _, why = SPLAT_RENAMED_KEYS[key]
            return f"'{key}' was moved for the splats {why} (see CHANGELOG.md): use {new}"
    return None
