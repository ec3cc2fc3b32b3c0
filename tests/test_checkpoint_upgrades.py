"""Checkpoints written by 0.3 keep loading: their run's model config, as every 0.3 preset composed it
(tests/fixtures/model_configs_0.3.json, written by the 0.3 code), is read as this version builds it."""

from __future__ import annotations

import json
from pathlib import Path

import pytest
from hydra.utils import instantiate
from omegaconf import OmegaConf

from nerf_lightning.checkpoints import upgraded_config
from nerf_lightning.config import compose_config

OLD = json.loads((Path(__file__).parent / "fixtures" / "model_configs_0.3.json").read_text())
# the model keys whose default changed since 0.3 (CHANGELOG): a 0.3 checkpoint keeps the value it was trained with
DEFAULTS_CHANGED = ("mask_loss",)


@pytest.mark.parametrize("preset", sorted(OLD))
def test_a_03_presets_model_config_reads_as_the_same_preset_composes_now(preset):
    """Upgraded, the 0.3 preset's model config is the preset's now (the same model, key for key; the keys whose default
    changed keep the checkpoint's value), so a 0.3 checkpoint builds the model it was trained as."""
    now = OmegaConf.to_container(compose_config([f"experiment={preset}", "paths.output_dir=/tmp/x"]).model, resolve=True)
    now.update({key: OLD[preset][key] for key in DEFAULTS_CHANGED if key in OLD[preset] and key in now})
    assert upgraded_config({"model": OLD[preset]})["model"] == now


def test_a_03_splat_and_fixed_shape_model_build_from_their_upgraded_configs():
    for preset in ("splat_object_cpu", "fast_blender_gpu"):
        model = instantiate(OmegaConf.create(upgraded_config({"model": OLD[preset]})["model"]))
        assert type(model).__name__ in ("SplatModule", "RadianceFieldModule")


@pytest.mark.parametrize(("fixed_shapes", "renderer"), [(True, "TableRenderer"), (False, "RoundsRenderer")])
def test_a_checkpoints_volume_renderer_of_before_0_3s_two_renderers_builds_the_one_it_chose(fixed_shapes, renderer):
    old = dict(OLD["fast"], renderer={"_target_": "nerf_lightning.rendering.VolumeRenderer", "early_stop_eps": 1e-4,
                                      "samples_per_round": 16, "gradient_scaling_distance": 0.0, "fixed_shapes": fixed_shapes})
    built = instantiate(OmegaConf.create(upgraded_config({"model": old})["model"]))
    assert type(built.renderer).__name__ == renderer
