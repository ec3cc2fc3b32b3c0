"""The shipped configs compose, and a mistyped key is refused with its name."""

import subprocess
import sys

import pytest
from hydra.errors import ConfigCompositionException

from nerf_lightning.config import compose_config


def test_train_config_composes_the_image_preset():
    cfg = compose_config(["experiment=image", "paths.output_dir=/tmp/x"])
    assert cfg.name == "image"
    assert cfg.model.optimizer.lr == 0.01 and cfg.data.batch_size == 10_000
    assert cfg.model.field.num_frequencies == 10 and cfg.model.field.hidden_width == 256
    assert cfg.trainer.max_steps == 1000 and list(cfg.data.val_steps) == [10, 100, 200, 400, 1000]
    assert cfg.data.seed == cfg.seed


def test_unknown_key_is_refused():
    with pytest.raises(ConfigCompositionException, match="model.field.levels"):
        compose_config(["model.field.levels=3", "paths.output_dir=/tmp/x"])


def test_unknown_key_on_the_command_line_exits_non_zero_naming_it(tmp_path):
    result = subprocess.run([sys.executable, "-m", "nerf_lightning.train", "data.pth=x.png"], cwd=tmp_path, capture_output=True, text=True)
    assert result.returncode != 0
    assert "data.pth" in result.stderr
    assert not (tmp_path / "outputs").exists() or not any((tmp_path / "outputs").rglob("metrics.json"))
