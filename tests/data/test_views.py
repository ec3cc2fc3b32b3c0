"""ViewDataModule: whole training views or patches of them, one a step, drawn by the step's seed; the validation
views every SceneDataModule serves carry their cameras."""

import pytest
import torch

from nerf_lightning.data import ViewDataModule
from nerf_lightning.data.batches import batch_seed
from nerf_lightning.geometry.rays import image_rays


def views_of(scene, **options):
    data = ViewDataModule(scene=lambda: scene, val_views=2, seed=3, **options)
    data.setup()
    return data


def test_a_step_gets_one_whole_training_view_with_its_camera(procedural_scene):
    data = views_of(procedural_scene)
    drawn = next(iter(data.train_dataloader()))
    assert set(drawn) == {"camera_index", "offset", "crop"} and drawn["camera_index"].shape == () and drawn["offset"].tolist() == [0, 0]
    batch = data.on_after_batch_transfer(drawn, 0)  # what Lightning calls on the model's device
    train, view = procedural_scene.train, int(drawn["camera_index"])
    assert batch["image"].shape == (100, 100, 3) and batch["image"].dtype == torch.float32
    assert (batch["height"], batch["width"]) == (100, 100) and batch["K"].shape == (3, 3) and batch["c2w"].shape == (4, 4)
    torch.testing.assert_close(batch["image"], train.images[view].float() / 255)
    assert torch.equal(batch["K"], train.K[view]) and torch.equal(batch["c2w"], train.c2w[view])


def test_a_patch_is_cut_with_its_camera_whose_rays_are_the_views_rays_at_those_pixels(procedural_scene):
    data = views_of(procedural_scene, patch_size=24)
    train = procedural_scene.train
    iterator = iter(data.train_dataloader())
    offsets = set()
    for _ in range(5):
        batch = data.on_after_batch_transfer(next(iterator), 0)
        view, (x0, y0) = int(batch["camera_index"]), batch["offset"].tolist()
        offsets.add((x0, y0))
        assert batch["image"].shape == (24, 24, 3) and (batch["height"], batch["width"]) == (24, 24)
        assert 0 <= x0 <= 100 - 24 and 0 <= y0 <= 100 - 24
        torch.testing.assert_close(batch["image"], train.images[view, y0 : y0 + 24, x0 : x0 + 24].float() / 255)
        torch.testing.assert_close(batch["K"][:2, 2], train.K[view, :2, 2] - torch.tensor([x0, y0]).float())
        patch_o, patch_d = image_rays(batch["K"][None], batch["c2w"][None], 24, 24)
        view_o, view_d = image_rays(train.K[view : view + 1], train.c2w[view : view + 1], 100, 100)
        torch.testing.assert_close(patch_o.reshape(24, 24, 3), view_o.reshape(100, 100, 3)[y0 : y0 + 24, x0 : x0 + 24])
        torch.testing.assert_close(patch_d.reshape(24, 24, 3), view_d.reshape(100, 100, 3)[y0 : y0 + 24, x0 : x0 + 24])
    assert len(offsets) > 1


def test_coarse_views_first_are_whole_views_averaged_with_their_cameras_then_patches(procedural_scene, monkeypatch):
    """data.coarse_scale / coarse_steps: before coarse_steps the whole view area-averaged by the scale, its camera's
    rays through the coarse pixels' centres those of the full view's pixel blocks' centres; from coarse_steps on,
    full-resolution patches as before."""
    data = views_of(procedural_scene, patch_size=24, coarse_scale=4, coarse_steps=3)
    train = procedural_scene.train
    drawn = next(iter(data.train_dataloader()))
    view = int(drawn["camera_index"])
    for step, expected in ((0, 4), (2, 4), (3, 1), (50, 1)):
        monkeypatch.setattr(data, "_steps_done", lambda step=step: step)
        assert data.scale_now() == expected
        batch = data.on_after_batch_transfer(dict(drawn), 0)
        if expected == 1:  # a full-resolution patch
            assert batch["image"].shape == (24, 24, 3) and "scale" not in batch
            continue
        assert batch["scale"] == 4 and batch["image"].shape == (25, 25, 3) and (batch["height"], batch["width"]) == (25, 25)
        assert batch["offset"].tolist() == [0, 0]
        full = train.images[view].float() / 255
        torch.testing.assert_close(batch["image"], full.reshape(25, 4, 25, 4, 3).mean(dim=(1, 3)))
        coarse_o, coarse_d = image_rays(batch["K"][None], batch["c2w"][None], 25, 25)
        # the full view's rays through the blocks' centres: the corner pixels' (1.5, 1.5) of each 4x4 block
        K = train.K[view].clone()
        K[:2, 2] -= 1.5  # a 100x100 view's pixel (4i + 1.5 + 0.5) is (4i + 2), a coarse pixel (i + 0.5) scaled by 4
        full_o, full_d = image_rays(K[None], train.c2w[view : view + 1], 100, 100)
        torch.testing.assert_close(coarse_d.reshape(25, 25, 3), full_d.reshape(100, 100, 3)[::4, ::4], atol=1e-5, rtol=1e-5)
        torch.testing.assert_close(coarse_o.reshape(25, 25, 3), full_o.reshape(100, 100, 3)[::4, ::4])


def test_a_coarse_schedule_of_several_scales_goes_down_step_by_step(procedural_scene, monkeypatch):
    """data.coarse_scale=[4, 2], data.coarse_steps=[2, 5]: averaged by 4 until step 2, by 2 until step 5, then
    patches; given as Hydra gives lists too."""
    from omegaconf import OmegaConf

    schedule = OmegaConf.create({"scale": [4, 2], "steps": [2, 5]})
    data = views_of(procedural_scene, patch_size=24, coarse_scale=schedule.scale, coarse_steps=schedule.steps)
    drawn = next(iter(data.train_dataloader()))
    view = int(drawn["camera_index"])
    full = procedural_scene.train.images[view].float() / 255
    for step, expected in ((0, 4), (1, 4), (2, 2), (4, 2), (5, 1), (9, 1)):
        monkeypatch.setattr(data, "_steps_done", lambda step=step: step)
        batch = data.on_after_batch_transfer(dict(drawn), 0)
        if expected == 1:
            assert batch["image"].shape == (24, 24, 3) and "scale" not in batch
            continue
        side = 100 // expected
        assert batch["scale"] == expected and batch["image"].shape == (side, side, 3)
        torch.testing.assert_close(batch["image"], full.reshape(side, expected, side, expected, 3).mean(dim=(1, 3)))
        torch.testing.assert_close(batch["K"][:2], procedural_scene.train.K[view, :2] / expected)


def test_draws_are_the_steps_own_so_a_resumed_run_draws_the_same(procedural_scene):
    data, again = views_of(procedural_scene, patch_size=16), views_of(procedural_scene, patch_size=16)
    first = list(iter(data.train_dataloader()))[:40]
    second = list(iter(again.train_dataloader()))[:40]
    assert all(torch.equal(a[key], b[key]) if torch.is_tensor(a[key]) else a[key] == b[key] for a, b in zip(first, second) for key in a)
    assert len({int(b["camera_index"]) for b in second}) > 10  # views differ from step to step
    # the batch of step s is the one its seed draws, whatever step the stream started at
    generator = torch.Generator()
    for step in (0, 7, 39):
        generator.manual_seed(batch_seed(3, 0, step))
        drawn = data.draw_batch(generator)
        assert all(torch.equal(drawn[key], second[step][key]) for key in drawn if key != "crop")
        assert list(drawn["crop"]) == list(second[step]["crop"]) == [int(drawn["camera_index"]), *drawn["offset"].tolist()]


def test_a_patch_larger_than_the_views_and_a_missing_root_are_refused(procedural_scene):
    with pytest.raises(ValueError, match=r"data.patch_size=101 does not fit the 100x100 training views"):
        views_of(procedural_scene, patch_size=101)
    with pytest.raises(ValueError, match="data.patch_size must be >= 1"):
        ViewDataModule(scene=lambda: procedural_scene, patch_size=0)
    for scale, steps, message in ((1.5, 10, "must be whole numbers >= 1"), (2, -1, "must be whole numbers >= 1"),
                                  ([2, 4], [10, 20], "must go down"), ([4, 2], [20, 10], "must go down"),
                                  ([4, 2], [10], "one step a scale")):
        with pytest.raises(ValueError, match=f"data.coarse_scale .*{message}"):
            ViewDataModule(scene=lambda: procedural_scene, coarse_scale=scale, coarse_steps=steps)
    with pytest.raises(ValueError, match=r"data.coarse_scale=101 is larger than the 100x100 training views"):
        views_of(procedural_scene, coarse_scale=101, coarse_steps=10)

    def load_files(root):
        return procedural_scene

    with pytest.raises(ValueError, match="data.root: load_files needs a folder or file: set data.root"):
        ViewDataModule(scene=load_files).setup()


def test_validation_views_carry_their_cameras(procedural_scene):
    data = views_of(procedural_scene)
    views = data.validation_views()
    for index, batch in enumerate(data.val_dataloader()):
        assert batch["K"].shape == (3, 3) and batch["c2w"].shape == (4, 4)
        assert torch.equal(batch["K"], views.K[index]) and torch.equal(batch["c2w"], views.c2w[index])
        assert data.on_after_batch_transfer(batch, 0) is batch


def test_data_views_config_serves_any_format(tmp_path, procedural_scene):
    from hydra.utils import instantiate

    from nerf_lightning.config import compose_config
    from nerf_lightning.data.formats import save_npz

    path = save_npz(procedural_scene, tmp_path / "course.npz")
    cfg = compose_config(["data=views", "data/scene=npz", f"data.root={path}", "data.patch_size=32", "paths.output_dir=/tmp/unused"])
    assert cfg.data.seed == cfg.seed and cfg.data.scene._target_.endswith("load_npz")
    data = instantiate(cfg.data)
    assert isinstance(data, ViewDataModule) and data.patch_size == 32
    data.setup()
    assert data.on_after_batch_transfer(next(iter(data.train_dataloader())), 0)["image"].shape == (32, 32, 3)
    assert data.space is not None and len(data.render_views()) == len(procedural_scene.splits["test"])


def test_a_radiance_field_refuses_views_in_one_line(make_config, scene_cache, monkeypatch):
    from nerf_lightning.training import train

    monkeypatch.setenv("NERF_LIGHTNING_CACHE", str(scene_cache))
    cfg = make_config("model=ngp", "data=views", "data/scene=procedural", "data.scene.max_views=12", "trainer.max_steps=2",
                      "trainer.enable_progress_bar=false")
    with pytest.raises(ValueError, match="a radiance field trains on random rays, and data=views serves whole training views"):
        train(cfg)
