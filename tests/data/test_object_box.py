"""The object's box from a masked capture's visual hull, the scene fitted to it, and rays cut to it."""

from __future__ import annotations

import dataclasses
import types

import pytest
import torch

from nerf_lightning.data import RayDataModule
from nerf_lightning.data.formats.turntable import OBJECT_BOUNDS, load_turntable
from nerf_lightning.data.object_box import fit_scene_to_box, visual_hull_box
from nerf_lightning.geometry.contraction import Contraction
from nerf_lightning.geometry.cameras import box_pixel_rectangles
from nerf_lightning.geometry.rays import image_rays, ray_aabb_intersect
from nerf_lightning.geometry.space import SceneSpace


@pytest.fixture(scope="module")
def turntable(tmp_path_factory):
    return load_turntable(cache_dir=tmp_path_factory.mktemp("turntable"))


def true_box(scene) -> tuple[torch.Tensor, torch.Tensor]:
    """The turntable object's box (its known bounds in its own frame) in the scene's world."""
    transform = scene.world_from_capture.double()
    corners = torch.cartesian_prod(*[torch.tensor([low, high], dtype=torch.float64) for low, high in zip(*OBJECT_BOUNDS)])
    corners = corners @ transform[:3, :3].T + transform[:3, 3]
    return corners.min(0).values, corners.max(0).values


def test_the_visual_hull_box_holds_the_object_and_little_of_the_room(turntable):
    box = visual_hull_box(turntable.train).double()
    low, high = true_box(turntable)
    # the disc and what stands on it lie inside (the hull is carved from above: below the disc it reaches further)
    assert (box[:3] <= low[:3] + 1e-3).all() and (box[3:] >= high - 1e-3).all(), (box, low, high)
    # the cameras stand in [-1, 1]^3: the box takes a small part of that cube, and is not much wider than the object
    assert float((box[3:] - box[:3]).prod()) < 0.1 * 8.0
    assert ((box[3:5] - box[:2]) < 1.5 * (high[:2] - low[:2])).all()


def test_fitting_moves_the_box_into_the_unit_cube_and_keeps_every_pixel_on_its_point(turntable):
    box = visual_hull_box(turntable.train)
    moved, fitted = fit_scene_to_box(turntable, box)
    assert torch.allclose((fitted[3:] + fitted[:3]) / 2, torch.zeros(3), atol=1e-5)
    assert abs(float((fitted[3:] - fitted[:3]).max()) - 2.0) < 1e-5
    # a point of the old world seen by a view is seen at the same pixel in the moved view, at the scaled distance
    scale = 2.0 / float((box[3:] - box[:3]).max())
    views, moved_views = turntable.train, moved.train
    origins, directions = image_rays(views.K[:1].double(), views.c2w[:1].double(), views.height, views.width)
    moved_origins, moved_directions = image_rays(moved_views.K[:1].double(), moved_views.c2w[:1].double(), views.height, views.width)
    centre = (box[:3].double() + box[3:].double()) / 2
    points = origins + 2.5 * directions
    assert torch.allclose(moved_origins + 2.5 * scale * moved_directions, (points - centre) * scale, atol=1e-5)
    # the capture's coordinates are where they were: the similarity composes with the loader's
    capture_point = torch.tensor([0.3, -0.2, 0.1], dtype=torch.float64)
    before = turntable.world_from_capture.double()[:3, :3] @ capture_point + turntable.world_from_capture.double()[:3, 3]
    after = moved.world_from_capture.double()[:3, :3] @ capture_point + moved.world_from_capture.double()[:3, 3]
    assert torch.allclose(after, (before - centre) * scale, atol=1e-5)
    assert moved.near == pytest.approx(turntable.near * scale) and moved.far == pytest.approx(turntable.far * scale)


def test_masks_that_hold_nothing_or_none_at_all_are_refused_by_name(turntable):
    with pytest.raises(ValueError, match="data.object_box=visual_hull needs the capture's masks"):
        visual_hull_box(dataclasses.replace(turntable.train, masks=None))
    black = torch.zeros_like(turntable.train.masks)
    with pytest.raises(ValueError, match="no point lies inside the masks"):
        visual_hull_box(dataclasses.replace(turntable.train, masks=black))


def test_rays_are_cut_to_the_bounds_and_a_miss_gets_an_empty_range():
    space = SceneSpace(near=0.1, far=10.0, bounds=[-1.0, -1.0, -1.0, 1.0, 1.0, 1.0])
    rays = space.rays(torch.tensor([[0.0, 0.0, -5.0], [0.0, 3.0, -5.0]]), torch.tensor([[0.0, 0.0, 1.0], [0.0, 0.0, 1.0]]))
    t_enter, t_exit = space.ray_range(rays)
    assert torch.allclose(t_enter, torch.tensor([4.0, t_enter[1].item()])) and float(t_exit[0]) == pytest.approx(6.0)
    assert float(t_exit[1]) == float(t_enter[1])  # misses the box: nothing to sample
    again = SceneSpace.from_state(space.state())
    assert torch.equal(again.bounds, space.bounds)
    assert SceneSpace.from_state({**space.state(), "bounds": None}).bounds is None  # a checkpoint from before
    with pytest.raises(ValueError, match="object_box"):
        SceneSpace(bounds=[-1.0, -1.0, -1.0, 1.0, 1.0, 1.0], contraction=Contraction())


def test_a_field_box_that_does_not_hold_the_object_is_refused_by_key():
    space = SceneSpace(near=0.1, far=10.0, bounds=[-0.5, -1.0, -0.3, 0.5, 1.0, 0.3])
    space.check_box(torch.tensor([-1.0, -1.0, -1.0, 1.0, 1.0, 1.0]), "model.field.aabb")
    with pytest.raises(ValueError, match=r"model.field.aabb is .* the object's box"):
        space.check_box(torch.tensor([-0.4, -0.4, -0.4, 0.4, 0.4, 0.4]), "model.field.aabb")


def test_evaluation_refuses_a_scene_that_no_longer_loads_where_the_model_learnt_it(turntable, make_config):
    from omegaconf import OmegaConf

    from nerf_lightning.checkpoints import load_run_data

    cfg = make_config("experiment=nerfacto_object_cpu", "data/scene=turntable")
    config = {"data": OmegaConf.to_container(cfg.data, resolve=True)}
    config["data"]["scene"] = {"_target_": "tests.data.test_object_box.cached_turntable", "_partial_": True}
    _CACHED.append(turntable)
    data = load_run_data(config)
    same = types.SimpleNamespace(space=data.space)
    assert load_run_data(config, same).space.bounds is not None
    moved = types.SimpleNamespace(space=SceneSpace(world_from_capture=torch.eye(4)))
    with pytest.raises(ValueError, match="no longer loads where the checkpoint learnt it"):
        load_run_data(config, moved)


_CACHED: list = []


def cached_turntable():
    return _CACHED[-1]


def test_masks_that_cover_the_photos_warn_that_they_are_no_object_outline(turntable, caplog):
    data = RayDataModule(scene=lambda: turntable, batch_size=256, masks="background", object_box="visual_hull")
    with caplog.at_level("WARNING"):
        data.setup()
    assert "are they an object's outline" not in caplog.text
    whole = dataclasses.replace(turntable, splits={name: dataclasses.replace(views, masks=torch.ones_like(views.masks))
                                                   for name, views in turntable.splits.items()})
    with caplog.at_level("WARNING"):
        RayDataModule(scene=lambda: whole, batch_size=256, masks="exclude", object_box="visual_hull").setup()
    assert "are they an object's outline" in caplog.text


def test_the_datamodule_fits_the_scene_only_with_masks_in_use(turntable):
    data = RayDataModule(scene=lambda: turntable, batch_size=256, masks="background", object_box="visual_hull")
    data.setup()
    assert data.space.bounds is not None and (data.space.bounds.abs() <= 1.0 + 1e-5).all()
    with pytest.raises(ValueError, match="data.object_box=visual_hull needs the capture's masks in use"):
        RayDataModule(scene=lambda: turntable, batch_size=256, masks="ignore", object_box="visual_hull").setup()
    with pytest.raises(ValueError, match="data.contract=false"):
        RayDataModule(scene=lambda: turntable, batch_size=256, masks="background", object_box="visual_hull", contract=True)
    with pytest.raises(ValueError, match="data.object_box must be one of"):
        RayDataModule(scene=lambda: turntable, batch_size=256, object_box="hull")
    unmasked = dataclasses.replace(turntable, splits={name: dataclasses.replace(views, masks=None) for name, views in turntable.splits.items()})
    with pytest.raises(ValueError, match="needs an object's masks, and .* has none"):
        RayDataModule(scene=lambda: unmasked, batch_size=256, masks="background", object_box="visual_hull").setup()


def test_rays_are_drawn_only_where_they_can_meet_the_object_box(turntable):
    data = RayDataModule(scene=lambda: turntable, batch_size=20_000, masks="background", object_box="visual_hull", seed=0)
    data.setup()
    train, box = data.scene.train, data.space.bounds
    height, width = train.height, train.width
    # every pixel whose ray meets the box lies in its view's rectangle, and the rectangles leave out most of the views
    rays_o, rays_d = image_rays(train.K, train.c2w, height, width)
    hits = []
    for view in range(len(train)):
        t_enter, t_exit = ray_aabb_intersect(rays_o[view], rays_d[view], box)
        hits.append((t_exit > t_enter.clamp(min=0.0)).reshape(height, width))
    hits = torch.stack(hits)  # (V, H, W)
    inside = torch.zeros_like(hits)
    for view, (x0, y0, x1, y1) in enumerate(data.rectangles.tolist()):
        inside[view, y0:y1, x0:x1] = True
    assert hits.any() and not (hits & ~inside).any()
    assert inside.float().mean() < 0.99, inside.float().mean()  # the procedural object's hull box is wide: most of each view
    # the drawn pixels all lie in the rectangles, and cover them uniformly: each pixel of the rectangles as likely
    drawn = torch.cat([next(iter(data.train_dataloader()))["pixel_index"] for _ in range(3)])
    flat_inside = inside.reshape(-1)
    assert flat_inside[drawn].all()
    counts = torch.bincount(drawn // (height * width), minlength=len(train)).double()
    expected = inside.reshape(len(train), -1).sum(1).double() / flat_inside.sum() * len(drawn)
    assert ((counts - expected).abs() < 5 * expected.sqrt() + 1).all(), (counts, expected)
    # the colours the model gets are those pixels' (the drawn index is the one the rays are made from)
    batch = data.on_after_batch_transfer({"pixel_index": drawn[:64]}, 0)
    t_enter, t_exit = ray_aabb_intersect(batch["rays_o"], batch["rays_d"], box)
    assert (t_exit > t_enter).float().mean() > 0.5


def test_a_box_behind_or_around_a_camera_gives_the_whole_view():
    K = torch.tensor([[[50.0, 0.0, 32.0], [0.0, 50.0, 32.0], [0.0, 0.0, 1.0]]]).expand(3, 3, 3)
    c2w = torch.eye(4).repeat(3, 1, 1)
    c2w[0, 2, 3] = -4.0  # the box 4 in front: a rectangle inside the view
    c2w[1, 2, 3] = 0.0  # the camera inside the box
    c2w[2, 2, 3] = 4.0  # the box behind the camera
    rectangles = box_pixel_rectangles(K, c2w, 64, 64, torch.tensor([-1.0, -1.0, -1.0, 1.0, 1.0, 1.0]))
    # in front: the near face (z = 3) spans 32 +- 50/3 px; widened by a pixel
    assert rectangles[0].tolist() == [14, 14, 50, 50]
    assert rectangles[1].tolist() == rectangles[2].tolist() == [0, 0, 64, 64]


def test_an_object_share_of_the_rays_is_drawn_on_the_masks(turntable):
    share = 0.75
    data = RayDataModule(scene=lambda: turntable, batch_size=8000, masks="background", object_box="visual_hull",
                         object_share=share, seed=0)
    data.setup()
    masks = data.scene.train.masks.reshape(-1)
    drawn = next(iter(data.train_dataloader()))["pixel_index"]
    assert drawn.shape == (8000,)
    # the share on the object, and the rest drawn as without it: on the masks as often as the masks fill the rectangles
    inside = torch.zeros_like(data.scene.train.masks)
    for view, (x0, y0, x1, y1) in enumerate(data.rectangles.tolist()):
        inside[view, y0:y1, x0:x1] = True
    rest = float(masks[inside.reshape(-1)].float().mean())
    expected = share + (1 - share) * rest
    on_masks = float(masks[drawn].float().mean())
    assert abs(on_masks - expected) < 0.02, (on_masks, expected)
    plain = RayDataModule(scene=lambda: turntable, batch_size=8000, masks="background", object_box="visual_hull", seed=0)
    plain.setup()
    assert abs(float(masks[next(iter(plain.train_dataloader()))["pixel_index"]].float().mean()) - rest) < 0.02
    # the batch's colours are the object's where the masks are: the object pixels drawn carry their mask
    batch = data.on_after_batch_transfer({"pixel_index": drawn}, 0)
    assert torch.equal(batch["object_mask"], masks[drawn])


def test_an_object_share_needs_masks_drawn_as_background_and_a_share_in_range(turntable):
    with pytest.raises(ValueError, match=r"data.object_share is the share .* in \[0, 1\]"):
        RayDataModule(scene=lambda: turntable, batch_size=256, masks="background", object_share=1.5)
    with pytest.raises(ValueError, match="data.object_share=0.5 draws rays on an object's masks, which need data.masks=background"):
        RayDataModule(scene=lambda: turntable, batch_size=256, masks="ignore", object_share=0.5).setup()
