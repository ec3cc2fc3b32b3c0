"""What draws a view (nerf_lightning.splats.draw): the tile rasteriser of the device where it runs, else the pairs
one (one warning); the first view drawn without gradients still takes the tiles; the model/rasterizer group builds the
choosers, and the keys that moved are answered; a checkpoint's config from before 0.4 builds the same choice."""

from __future__ import annotations

import warnings

import pytest
import torch
from hydra.utils import instantiate

from nerf_lightning.splats.draw import PairsRasterizer, TileRasterizer
from nerf_lightning.splats.rasterize_reference import rasterize_reference
from tests.splats.test_rasterize_pairs import gaussians
from tests.splats.test_rasterize_tiles import drawn, rasterize_triton_here


def test_auto_takes_tiles_on_a_cpu_triton_on_cuda_and_pytorch_elsewhere(monkeypatch):
    tiles, pairs = TileRasterizer(), PairsRasterizer()
    assert tiles.choose("cpu") == "tiles" and tiles.for_device("cpu").numba
    assert tiles.choose("mps") == pairs.choose("mps") == pairs.choose("cpu") == "pairs"
    monkeypatch.setattr(tiles.kernels, "triton", lambda: rasterize_triton_here)
    assert tiles.choose("cuda") == "triton" and pairs.choose("cuda") == "pairs"
    monkeypatch.setattr(tiles.kernels, "triton", lambda: None)  # Triton missing or failing there: PyTorch draws
    assert tiles.choose("cuda") == "pairs"


def test_the_rasterizer_group_builds_the_choosers_and_the_old_keys_are_answered():
    from nerf_lightning.config import compose_config, renamed_key_message

    for name, kind in (("auto", TileRasterizer), ("tiles", TileRasterizer), ("pairs", PairsRasterizer)):
        config = compose_config(["model=splat", f"model/rasterizer={name}", "model.rasterizer.max_pairs=1000",
                                 "model.rasterizer.antialiased=true", "paths.output_dir=/tmp/unused"])
        rasterizer = instantiate(config.model.rasterizer)
        assert type(rasterizer) is kind and (rasterizer.max_pairs, rasterizer.antialiased) == (1000, True)
    assert "use model/rasterizer=pairs" in renamed_key_message(["model.rasterizer=pairs"])
    assert "use model.rasterizer.max_pairs" in renamed_key_message(["model.max_pairs=10"])
    assert "use model.rasterizer.antialiased" in renamed_key_message(["model.antialiased=true"])
    assert renamed_key_message(["model/rasterizer=tiles", "model.rasterizer.max_pairs=10"]) is None
    with pytest.raises(ValueError, match="model.rasterizer.max_pairs must be >= 1, got 0"):
        PairsRasterizer(max_pairs=0)


def test_a_splat_checkpoints_config_from_before_0_4_builds_its_rasterizer():
    """0.3 wrote model.rasterizer as a name beside model.max_pairs and model.antialiased: a checkpoint's config with
    them builds the same choice (checkpoints.load_model upgrades it)."""
    from nerf_lightning.checkpoints import upgraded_config

    def upgraded_model_config(model):
        return upgraded_config({"model": {"_target_": "nerf_lightning.models.SplatModule", **model}})["model"]

    old = {"rasterizer": "pairs", "max_pairs": 500, "antialiased": True, "ssim_weight": 0.2}
    new = upgraded_model_config(old)
    rasterizer = instantiate(new["rasterizer"])
    assert type(rasterizer) is PairsRasterizer and (rasterizer.max_pairs, rasterizer.antialiased) == (500, True)
    assert "max_pairs" not in new and "antialiased" not in new and new["loss"]["ssim_weight"] == 0.2
    assert upgraded_model_config(new) == new and type(instantiate(upgraded_model_config({"rasterizer": "auto"})["rasterizer"])) is TileRasterizer


@pytest.mark.parametrize("mode", [torch.no_grad, torch.inference_mode])
def test_auto_takes_tiles_where_the_first_view_is_drawn_without_gradients(mode):
    """nerf-render, nerf-eval and the viewer draw their first view under no_grad (render_view) or inference_mode: the
    probe's backward pass must not fail there and send the whole process to the PyTorch rasteriser."""
    g = {key: value.detach() for key, value in gaussians(seed=11).items()}
    tiles = TileRasterizer()
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        with mode():
            assert tiles.choose("cpu") == "tiles"
            out = drawn(g, lambda *args: tiles.for_device("cpu").rasterize(*args), 20, 24)
    torch.testing.assert_close(out["rgb"], drawn(g, rasterize_reference, 20, 24)["rgb"], atol=1e-5, rtol=1e-5)


def test_without_numba_one_warning_then_the_pytorch_rasteriser(monkeypatch):
    import builtins

    real_import = builtins.__import__

    def no_numba(name, *args, **kwargs):
        if name == "numba" or name.startswith("numba."):
            raise ImportError("No module named 'numba'")
        return real_import(name, *args, **kwargs)

    monkeypatch.delitem(__import__("sys").modules, "nerf_lightning.splats.rasterize_tiles")
    monkeypatch.delattr(__import__("nerf_lightning.splats").splats, "rasterize_tiles")
    monkeypatch.setattr(builtins, "__import__", no_numba)
    g = gaussians(seed=10)
    tiles = TileRasterizer()
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        out = drawn(g, lambda *args: tiles.for_device("cpu").rasterize(*args), 20, 24)
        drawn(g, lambda *args: tiles.for_device("cpu").rasterize(*args), 20, 24)
    said = [w for w in caught if "tile rasteriser is unavailable" in str(w.message)]
    assert len(said) == 1 and "pip install numba" in str(said[0].message)
    assert tiles.choose("cpu") == "pairs" and not tiles.for_device("cpu").numba
    torch.testing.assert_close(out["rgb"], drawn(g, rasterize_reference, 20, 24)["rgb"], atol=1e-5, rtol=1e-5)


@pytest.mark.skipif(torch.cuda.is_available(), reason="where CUDA is, the GPU tile rasteriser may run")
def test_on_cuda_without_a_gpu_rasteriser_one_warning_then_the_pytorch_rasteriser():
    tiles = TileRasterizer()
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        assert tiles.choose("cuda") == tiles.choose("cuda") == "pairs"
    said = [w for w in caught if "GPU tile rasteriser is unavailable" in str(w.message)]
    assert len(said) == 1
