"""The masked object presets (splat_object_cpu, nerfacto_object_cpu) trained end to end, as shipped but for their
length and sizes, on a small masked capture the tests write: each scores its held-out views inside the masks above what
the training pixels' mean colour scores there, the trivial baseline, computed on the same views."""

from __future__ import annotations

import math
from pathlib import Path

import pytest
import torch
from hydra.utils import instantiate

from nerf_lightning.data.formats.procedural import camera_positions, render_views
from nerf_lightning.data.image_stack import as_float_rgb
from nerf_lightning.geometry.cameras import look_at, opengl_to_opencv
from nerf_lightning.io import write_json, write_png
from nerf_lightning.metrics import image_metrics
from nerf_lightning.training import train

VIEWS, SIZE = 40, 48
ROOM = 0.5  # the grey the object is photographed over: what its masks take away with data.masks=background


def write_masked_capture(root: Path, n_views: int = VIEWS, size: int = SIZE, fov_degrees: float = 50.0) -> Path:
    """The procedural scene's objects ray-traced from ``n_views`` cameras around them, over a grey room, as a
    transforms.json capture with a mask a photo (``mask_path``, white on the object): what nerf-process-data writes
    for a masked object."""
    focal = 0.5 * size / math.tan(0.5 * math.radians(fov_degrees))
    K = torch.tensor([[focal, 0.0, size / 2.0], [0.0, focal, size / 2.0], [0.0, 0.0, 1.0]], dtype=torch.float64)
    c2w = look_at(camera_positions(n_views))  # OpenCV
    rgba = render_views(c2w, K.expand(n_views, 3, 3), size, size)["rgba"]  # (N, H, W, 4)
    frames = []
    for index in range(n_views):
        rgb, alpha = rgba[index, ..., :3], rgba[index, ..., 3:]
        write_png(root / "images" / f"{index:03d}.png", rgb + (1.0 - alpha) * ROOM)
        write_png(root / "masks" / f"{index:03d}.png", alpha[..., 0])
        frames.append({"file_path": f"images/{index:03d}.png", "mask_path": f"masks/{index:03d}.png",
                       "transform_matrix": opengl_to_opencv(c2w[index]).tolist()})
    write_json(root / "transforms.json", {"camera_model": "PINHOLE", "fl_x": focal, "fl_y": focal, "cx": size / 2.0, "cy": size / 2.0,
                                          "w": size, "h": size, "frames": frames})
    return root


@pytest.fixture(scope="module")
def masked_capture(tmp_path_factory) -> Path:
    return write_masked_capture(tmp_path_factory.mktemp("masked") / "capture")


def mean_colour_score(datamodule) -> float:
    """psnr_masked of the training pixels' mean colour inside the masks, over the views validation scores: a model
    that learnt nothing of the object but its average colour."""
    train_views = datamodule.scene.train
    colour = as_float_rgb(train_views.images[train_views.masks]).mean(dim=0)  # (3,)
    scores = [float(image_metrics(colour.expand_as(batch["image"]), batch["image"], mask=batch["object_mask"])["psnr_masked"])
              for batch in datamodule.val_dataloader()]
    return sum(scores) / len(scores)


# the preset's own method, shortened: its steps, batch and validation sized for seconds on 2 cores. Each clears the
# mean colour by 2 to 3 dB in these steps (15.1 and 15.9 dB against 12.9); the bar asks for 1
PRESETS = {
    "splat_object_cpu": ["trainer.max_steps=300", "data.patch_size=null", "model.start.random.count=2000"],
    "nerfacto_object_cpu": ["trainer.max_steps=150", "data.batch_size=512", "model.sampler.bake_resolution=16"],
}
MARGIN_DB = 1.0


@pytest.mark.parametrize("preset", sorted(PRESETS))
def test_an_object_preset_learns_its_held_out_views_inside_the_masks(preset, masked_capture, make_config):
    cfg = make_config(f"experiment={preset}", *PRESETS[preset], "data/scene=transforms", f"data.root={masked_capture}",
                      "data.scene.downscale=1", "data.scene.holdout_every=8", "data.val_views=5", f"data.val_every={10**6}",
                      "logger={}", "callbacks=none", "trainer.enable_progress_bar=false", "trainer.enable_model_summary=false",
                      "++trainer.num_sanity_val_steps=0")
    assert cfg.data.masks == "background"  # the preset's masks, not the test's
    metrics = train(cfg)
    datamodule = instantiate(cfg.data)
    datamodule.setup("fit")
    baseline = mean_colour_score(datamodule)
    scored = metrics["val/psnr_masked"]
    assert metrics["step"] == cfg.trainer.max_steps
    assert scored > baseline + MARGIN_DB, (f"{preset}: {scored:.2f} dB inside the masks of the held-out views, the bar "
                                           f"{baseline + MARGIN_DB:.2f} (the training pixels' mean colour scores {baseline:.2f})")


# A walk round a masked object with a wide lens from near (90 degrees, 2 object-radii away): the views are mostly
# background, and with data.masks=background that background is black. Trained with the colours alone, nerfacto's
# field fell into the empty scene in its first steps and never left it (a black render, every held-out view 15 dB,
# whatever the length: 3 seeds of 3 at 64 px, 3 of 4 at 192 px); the masks' opacity loss (model.mask_loss, 0.01 by
# default for the hash-grid models) lifts it out within a hundred steps.
WIDE_TURNTABLE = {"size": 64, "fov_degrees": 90.0, "distance": 2.0}


def black_render_score(datamodule) -> float:
    """val/psnr (the whole image) of an empty field's render, black everywhere, over the views validation scores."""
    scores = [float(image_metrics(torch.zeros_like(batch["image"]), batch["image"])["psnr"]) for batch in datamodule.val_dataloader()]
    return sum(scores) / len(scores)


def test_a_masked_walk_round_is_not_left_empty(tmp_path, make_config):
    from nerf_lightning.data.formats import make_turntable_capture

    capture = make_turntable_capture(tmp_path / "capture", **WIDE_TURNTABLE)
    # 150 steps of the preset's 4000-step schedule: the learning rate the collapse happened at, not a schedule decayed
    # in 150 steps, whose smaller rates let the field out of the empty scene anyway
    cfg = make_config("experiment=nerfacto_360_cpu", "data/scene=transforms", f"data.root={capture}", "data.masks=background",
                      "trainer.max_steps=150", "model.scheduler.steps=4000", "data.batch_size=256", "data.val_views=5",
                      f"data.val_every={10**6}", "logger={}", "callbacks=none", "trainer.enable_progress_bar=false",
                      "trainer.enable_model_summary=false", "++trainer.num_sanity_val_steps=0")
    metrics = train(cfg)
    datamodule = instantiate(cfg.data)
    datamodule.setup("fit")
    empty = black_render_score(datamodule)
    # an empty field scores the black render's PSNR (15.8 dB here, and so did the run with model.mask_loss=0); with the
    # masks' loss the field scores 25.6
    assert metrics["val/psnr"] > empty + 3.0, (f"{metrics['val/psnr']:.2f} dB on the held-out views, an empty field's black render "
                                               f"{empty:.2f}: the field was left (nearly) empty")
