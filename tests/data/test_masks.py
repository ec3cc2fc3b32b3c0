"""Masks: read from transforms.json's mask_path and an LLFF capture's masks/ folder, then used by training as
``data.masks=exclude`` (rays drawn among the masked pixels, a view's loss over them) or ``background`` (the pixels
outside show the background colour), and scored over the whole image and over the mask in evaluation."""

import math

import imageio.v3 as iio
import numpy as np
import pytest
import torch

from nerf_lightning.data import RayDataModule, ViewDataModule
from nerf_lightning.data.formats import load_llff, load_transforms
from nerf_lightning.data.image_stack import as_float_rgb
from nerf_lightning.data.images import load_mask
from nerf_lightning.data.masks import resolve_mode
from nerf_lightning.io import write_png
from nerf_lightning.metrics import image_metrics
from tests.data.test_llff import write_llff
from tests.data.test_transforms import write_transforms

ROOM = torch.tensor([0.2, 0.6, 0.3])  # what the photos show outside the object


def object_masks(views):
    """(N, H, W) bool: the pixels that see the procedural scene's surfaces (finite true depth)."""
    return torch.isfinite(views.depth)


def photos_with_a_room(views):
    """(N, H, W, 3) the views' images with ROOM where they see no surface: a capture whose background is not empty."""
    masks = object_masks(views)
    return torch.where(masks[..., None], as_float_rgb(views.images), ROOM)


@pytest.fixture(scope="module")
def masked_capture(procedural_scene, tmp_path_factory):
    """Twelve procedural views as a transforms.json capture with a room around the object and masks/ beside images/."""
    views = procedural_scene.train.subset(list(range(12)))
    root = tmp_path_factory.mktemp("masked") / "capture"
    masks = object_masks(views)
    per_frame = {index: {"mask_path": f"masks/{index:04d}.png"} for index in range(len(views))}
    write_transforms(views, root, images=photos_with_a_room(views), per_frame=per_frame)
    for index, mask in enumerate(masks):
        write_png(root / "masks" / f"{index:04d}.png", mask.float())
    return root, masks


def test_transforms_masks_load_and_downscale_with_their_images(masked_capture):
    root, masks = masked_capture
    scene = load_transforms(root, downscale=1, holdout_every=4)
    every = torch.cat([scene.train.masks, scene.splits["val"].masks])
    assert every.dtype == torch.bool and every.shape == (12, *masks.shape[1:])
    assert sorted(map(tuple, every.reshape(12, -1).tolist())) == sorted(map(tuple, masks.reshape(12, -1).tolist()))
    halved = load_transforms(root, downscale=2, holdout_every=0)
    assert halved.train.masks.shape == (12, masks.shape[1] // 2, masks.shape[2] // 2)
    # a block is the object where at least half of it is: as the area-averaged mask thresholded
    block = masks[0].reshape(masks.shape[1] // 2, 2, masks.shape[2] // 2, 2).float().mean(dim=(1, 3)) >= 0.5
    assert torch.equal(halved.train.masks[0], block)


def test_bad_masks_are_named(masked_capture, tmp_path):
    import json
    import shutil

    root, _ = masked_capture
    copy = tmp_path / "copy"
    shutil.copytree(root, copy)
    meta = json.loads((copy / "transforms.json").read_text())
    del meta["frames"][3]["mask_path"]
    (copy / "transforms.json").write_text(json.dumps(meta))
    with pytest.raises(ValueError, match=r"11 frames have a 'mask_path' but 1 do not \(images/0003.png\)"):
        load_transforms(copy)
    meta["frames"][3]["mask_path"] = "masks/missing.png"
    (copy / "transforms.json").write_text(json.dumps(meta))
    with pytest.raises(FileNotFoundError, match="missing.png"):
        load_transforms(copy)
    meta["frames"][3]["mask_path"] = "masks/small.png"
    (copy / "transforms.json").write_text(json.dumps(meta))
    write_png(copy / "masks" / "small.png", torch.ones(10, 12))
    with pytest.raises(ValueError, match=r"small.png is 12x10 but its image is 100x100"):
        load_transforms(copy)


def test_mask_files_in_either_convention_and_with_jpeg_noise(tmp_path):
    truth = torch.zeros(16, 20, dtype=torch.bool)
    truth[4:12, 5:15] = True
    iio.imwrite(tmp_path / "white.png", truth.numpy().astype(np.uint8) * 255)
    iio.imwrite(tmp_path / "ones.png", truth.numpy().astype(np.uint8))
    iio.imwrite(tmp_path / "noisy.jpg", truth.numpy().astype(np.uint8) * 255, quality=60)
    rgba = np.zeros((16, 20, 4), np.uint8)
    rgba[..., 3] = truth.numpy() * 255
    iio.imwrite(tmp_path / "alpha.png", rgba)
    for name in ("white.png", "ones.png", "noisy.jpg", "alpha.png"):
        assert torch.equal(load_mask(tmp_path / name), truth), name
    with pytest.raises(ValueError, match="could not read mask"):
        (tmp_path / "broken.png").write_bytes(b"not a png")
        load_mask(tmp_path / "broken.png")


def test_llff_masks_folder_matches_images_by_stem_at_full_size(procedural_scene, tmp_path):
    views = procedural_scene.train.subset(list(range(6)))
    root = write_llff(views, tmp_path / "capture", downscale=2)  # images_2/ of 100x100: the full size is 200x200
    (root / "masks").mkdir()
    full = object_masks(views).repeat_interleave(2, dim=1).repeat_interleave(2, dim=2)
    for index, mask in enumerate(full):
        iio.imwrite(root / "masks" / f"image{index:03d}.png", mask.numpy().astype(np.uint8) * 255)
    scene = load_llff(root, downscale=2, holdout_every=0)
    assert torch.equal(scene.train.masks, object_masks(views))
    (root / "masks" / "image004.png").unlink()
    with pytest.raises(ValueError, match=r"masks has no mask for 1 of the 6 images \(image004.png\)"):
        load_llff(root, downscale=2, holdout_every=0)


def test_a_mode_needs_masks_and_null_means_exclude_where_there_are_some():
    assert resolve_mode(None, True, "x") == "exclude" and resolve_mode(None, False, "x") is None
    assert resolve_mode("ignore", True, "x") is None and resolve_mode("background", True, "x") == "background"
    with pytest.raises(ValueError, match="data.masks=background: lego has no masks"):
        resolve_mode("background", False, "lego")
    with pytest.raises(ValueError, match="data.masks must be one of exclude, background, ignore or null, got 'alpha'"):
        resolve_mode("alpha", True, "lego")


def scene_of(root):
    return lambda: load_transforms(root, holdout_every=4, background=(1.0, 0.0, 1.0))


def test_exclude_draws_rays_among_the_masked_pixels_alone(masked_capture):
    root, _ = masked_capture
    data = RayDataModule(scene=scene_of(root), batch_size=4096, masks="exclude")
    data.setup()
    batch = data.on_after_batch_transfer(next(iter(data.train_dataloader())), 0)
    assert bool(data.scene.train.masks.reshape(-1)[data.draw_batch(torch.Generator().manual_seed(0))["pixel_index"]].all())
    assert not torch.isclose(batch["rgb"], ROOM, atol=0.01).all(dim=-1).any()  # no ray shows the room
    assert "object_mask" not in batch and "loss_mask" not in batch  # every ray is of the object


def test_background_shows_the_background_colour_outside_the_masks(masked_capture):
    root, _ = masked_capture
    data = RayDataModule(scene=scene_of(root), batch_size=4096, masks="background")
    data.setup()
    batch = data.on_after_batch_transfer(next(iter(data.train_dataloader())), 0)
    outside = ~batch["object_mask"]
    assert 0.1 < float(outside.float().mean()) < 0.95  # rays are drawn over every pixel
    assert torch.equal(batch["rgb"][outside], torch.tensor([1.0, 0.0, 1.0]).expand(int(outside.sum()), 3))
    validation = next(iter(data.val_dataloader()))
    assert torch.equal(validation["image"][~validation["object_mask"]].unique(dim=0), torch.tensor([[1.0, 0.0, 1.0]]))


@pytest.mark.parametrize("mode", ["exclude", "background"])
def test_views_and_patches_carry_their_masks(masked_capture, mode):
    root, _ = masked_capture
    data = ViewDataModule(scene=scene_of(root), patch_size=40, masks=mode)
    data.setup()
    batch = data.on_after_batch_transfer(next(iter(data.train_dataloader())), 0)
    view, x0, y0 = batch["camera_index"].item(), *batch["offset"].tolist()
    mask = data.scene.train.masks[view, y0 : y0 + 40, x0 : x0 + 40]
    if mode == "exclude":
        assert torch.equal(batch["loss_mask"], mask) and "object_mask" not in batch
        assert torch.allclose(batch["image"], as_float_rgb(data.scene.train.images[view, y0 : y0 + 40, x0 : x0 + 40]))
    else:  # as a ray batch has it
        assert torch.equal(batch["object_mask"], mask) and "loss_mask" not in batch
        assert torch.equal(batch["image"][~mask], torch.tensor([1.0, 0.0, 1.0]).expand(int((~mask).sum()), 3))


def test_masked_metrics_cover_the_mask_alone():
    target = torch.rand(32, 32, 3)
    rgb = target.clone()
    mask = torch.zeros(32, 32, dtype=torch.bool)
    mask[8:24, 8:24] = True
    rgb[~mask] = 1.0 - rgb[~mask]  # wrong outside the mask only
    rgb[mask] += 0.01
    metrics = image_metrics(rgb, target, mask=mask)
    assert float(metrics["psnr_masked"]) == pytest.approx(40.0, abs=0.01)
    assert float(metrics["psnr"]) < 15.0
    assert math.isnan(float(image_metrics(rgb, target, mask=torch.zeros_like(mask))["psnr_masked"]))
