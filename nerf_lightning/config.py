"""Composing the shipped Hydra configs from Python (tests, benchmarks, notebooks)."""

from __future__ import annotations

from collections.abc import Sequence

from hydra import compose, initialize_config_module
from omegaconf import DictConfig


def compose_config(overrides: Sequence[str] = (), config_name: str = "train") -> DictConfig:
    """The config ``nerf-train`` would run with these overrides. Set ``paths.output_dir`` among them:
    outside a Hydra run there is no run folder to default to."""
    with initialize_config_module(config_module="nerf_lightning.conf", version_base="1.3"):
        return compose(config_name=config_name, overrides=list(overrides))
