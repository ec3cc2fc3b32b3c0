"""RayDataModule: random rays over all training pixels, whole held-out views, render paths."""

import pytest
import torch

from nerf_lightning.data import RayDataModule
from nerf_lightning.geometry import pinhole_camera
from nerf_lightning.geometry.paths import look_at_point


@pytest.fixture
def rays(procedural_scene):
    data = RayDataModule(scene=lambda: procedural_scene, batch_size=4096, val_views=3, seed=0)
    data.setup()
    return data


def test_training_batches(rays, procedural_scene):
    drawn = next(iter(rays.train_dataloader()))
    assert set(drawn) == {"pixel_index"} and drawn["pixel_index"].shape == (4096,)  # the loader draws pixels only
    batch = rays.on_after_batch_transfer(drawn, 0)  # what Lightning calls on the model's device
    assert batch["rays_o"].shape == batch["rays_d"].shape == batch["rgb"].shape == (4096, 3)
    torch.testing.assert_close(batch["rays_d"].norm(dim=-1), torch.ones(4096))
    assert 0 <= batch["rgb"].min() and batch["rgb"].max() <= 1
    # every ray starts at a training camera and its colour is that camera's pixel the ray goes through
    train = procedural_scene.train
    view = (batch["rays_o"][:, None, :] - train.c2w[None, :, :3, 3]).norm(dim=-1).argmin(dim=1)
    camera = pinhole_camera(train.K[view], train.c2w[view], train.height, train.width)
    uv = camera.project((batch["rays_o"] + 3.0 * batch["rays_d"])[:, None])[:, 0]
    torch.testing.assert_close(uv - uv.floor(), torch.full_like(uv, 0.5), atol=1e-3, rtol=0)  # pixel centres
    rows, cols = uv[:, 1].long(), uv[:, 0].long()
    torch.testing.assert_close(batch["rgb"], train.images[view, rows, cols].float() / 255)  # the uint8 pixel, as floats


def test_rays_are_drawn_uniformly_over_all_views(rays, procedural_scene):
    counts = torch.zeros(len(procedural_scene.train))
    iterator = iter(rays.train_dataloader())
    train = procedural_scene.train
    for _ in range(10):
        batch = rays.on_after_batch_transfer(next(iterator), 0)
        view = (batch["rays_o"][:, None, :] - train.c2w[None, :, :3, 3]).norm(dim=-1).argmin(dim=1)
        counts += torch.bincount(view, minlength=len(train))
    expected = counts.sum() / len(train)  # 512 per view
    assert (counts - expected).abs().max() < 5 * expected.sqrt()  # within 5 sigma of a uniform draw


def test_validation_batches_are_whole_held_out_views(rays, procedural_scene):
    batches = list(rays.val_dataloader())
    views = rays.validation_views()
    val = procedural_scene.splits["val"]
    assert len(batches) == 3 and views.names == [val.names[0], val.names[4], val.names[9]]  # spread over the split
    for index, batch in enumerate(batches):
        assert "rays_o" not in batch and batch["image"].shape == (100, 100, 3)  # the camera: its rays are made where it renders
        assert (batch["height"], batch["width"], batch["index"]) == (100, 100, index)
        assert torch.equal(batch["K"], views.K[index]) and torch.equal(batch["c2w"], views.c2w[index])  # the camera, for models that render views
        torch.testing.assert_close(batch["image"], views.images[index].float() / 255)
        torch.testing.assert_close(batch["depth"], views.depth[index])


@pytest.mark.parametrize("path", ["orbit", "spiral"])
def test_generated_render_paths_look_at_the_scene(rays, path):
    views = rays.render_views(path, n_frames=24)
    assert len(views) == 24 and views.images is None
    torch.testing.assert_close(look_at_point(views.c2w), torch.zeros(3), atol=0.05, rtol=0)
    radius = views.c2w[:, :3, 3].norm(dim=-1)
    torch.testing.assert_close(radius, torch.full_like(radius, 4.0), atol=0.05, rtol=0)


def test_test_render_path_uses_the_test_cameras(rays, procedural_scene):
    views = rays.render_views("test")
    assert torch.equal(views.c2w, procedural_scene.splits["test"].c2w)


def test_rays_of_drawn_pixels_equal_the_rays_of_their_whole_images(procedural_scene):
    from nerf_lightning.geometry.rays import image_rays, indexed_pixel_rays

    views = procedural_scene.train.subset([0, 5, 9])
    every_o, every_d = (rays.reshape(-1, 3) for rays in image_rays(views.K, views.c2w, views.height, views.width))
    index = torch.randint(0, len(views) * views.height * views.width, (500,), generator=torch.Generator().manual_seed(0))
    rays_o, rays_d = indexed_pixel_rays(views.K, views.c2w, views.height, views.width, index)
    torch.testing.assert_close(rays_o, every_o[index])
    torch.testing.assert_close(rays_d, every_d[index])


def test_the_drawn_pixels_are_the_steps_seeded_draw(rays, procedural_scene):
    from nerf_lightning.data import SceneDataModule
    from nerf_lightning.data.batches import batch_seed

    assert isinstance(rays, SceneDataModule)
    pixels = len(procedural_scene.train) * 100 * 100
    for step, drawn in zip(range(3), rays.train_dataloader()):
        expected = torch.randint(0, pixels, (4096,), generator=torch.Generator().manual_seed(batch_seed(0, 0, step)))
        assert torch.equal(drawn["pixel_index"], expected)
