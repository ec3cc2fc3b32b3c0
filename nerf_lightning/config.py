"""Composing the shipped Hydra configs from Python (tests, benchmarks, notebooks)."""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path

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


# Keys of nerf-lightning 0.1 that 0.2 moved (samplers and the scene space became objects): old key -> (the key now, a
# note), where the rest of a longer old key carries over to the new one
RENAMED_KEYS = {
    "model.fine_field": ("model.sampler.coarse_field", "with model/sampler=hierarchical"),
    "model.n_samples": ("model.sampler.n_samples", ""),
    "model.n_fine_samples": ("model.sampler.n_fine_samples", "with model/sampler=hierarchical"),
    "model.occupancy_grid": ("model.sampler.grid", "with model/sampler=occupancy_grid"),
    "model.render_step_size": ("model.sampler.step_size", ""),
    "model.cone_angle": ("model.sampler.cone_angle", ""),
    "model.alpha_threshold": ("model.sampler.alpha_threshold", ""),
    "model.early_stop_eps": ("model.renderer.early_stop_eps", ""),
    "model.samples_per_round": ("model.renderer.samples_per_round", ""),
    "model.field.contracted": ("data.contract", "with model.field.aabb=[-2,-2,-2,2,2,2], the contraction's cube"),
    **{f"model.field.{key}": (f"model.field.encoding.{key}", "")
       for key in ("n_levels", "features_per_level", "log2_table_size", "base_resolution", "max_resolution")},
}


def renamed_key_message(overrides: Sequence[str]) -> str | None:
    """The first command-line override that uses a key 0.2 moved, as a sentence saying what to write instead; or None."""
    for override in overrides:
        key = override.split("=", 1)[0].lstrip("+~").split("@", 1)[0]
        for old, (new, note) in RENAMED_KEYS.items():
            if key == old or key.startswith(old + "."):
                now = new + key[len(old):] + (f" ({note})" if note else "")
                return f"'{key}' was moved in nerf-lightning 0.2, when samplers and the scene space became objects (see the README): use {now}"
    return None
