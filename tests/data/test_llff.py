"""LLFF: the procedural scene written as poses_bounds.npy + images_<k>/ loads back to the same cameras; fern."""

import numpy as np
import pytest
import torch

from nerf_lightning.data.formats import load_llff
from nerf_lightning.data.formats.llff import write_poses_bounds
from nerf_lightning.data.formats.shared import apply_similarity
from nerf_lightning.geometry.rays import image_rays
from nerf_lightning.geometry.space import SceneSpace
from nerf_lightning.io import write_png
from tests.conftest import SHARED_DATA


def write_llff(views, root, downscale=2):
    """The views as an LLFF capture whose images are the ``images_<downscale>`` of a capture ``downscale`` times larger."""
    folder = root / f"images_{downscale}"
    folder.mkdir(parents=True)
    for index, image in enumerate(views.images):
        write_png(folder / f"image{index:03d}.png", image)
    bounds = np.tile([2.0, 6.0], (len(views), 1))
    write_poses_bounds(root / "poses_bounds.npy", views.c2w, downscale * views.height, downscale * views.width,
                       downscale * float(views.K[0, 0, 0]), bounds)
    return root


def write_forward_capture(procedural_scene, tmp_path):
    """The procedural cameras within 35 degrees of the first one, a forward-facing capture, written as LLFF into
    ``tmp_path / "capture"``."""
    train_views = procedural_scene.train
    axes = torch.nn.functional.normalize(train_views.c2w[:, :3, 2], dim=-1)
    close = (axes @ axes[0] > np.cos(np.radians(35))).nonzero()[:, 0].tolist()
    return write_llff(train_views.subset(close), tmp_path / "capture")


def test_llff_round_trip_without_recentring_gives_the_same_cameras_and_rays(procedural_scene, tmp_path):
    views = procedural_scene.train.subset(list(range(12)))
    root = write_llff(views, tmp_path / "capture")
    scene = load_llff(root, downscale=2, holdout_every=0, bd_factor=None, recentre=False)
    loaded = scene.train
    assert (loaded.height, loaded.width) == (views.height, views.width) and "val" not in scene.splits
    torch.testing.assert_close(loaded.K, views.K)
    torch.testing.assert_close(loaded.c2w, views.c2w, atol=1e-5, rtol=0)
    assert torch.equal(loaded.images, views.images)  # uint8, through 8-bit PNG
    rays = image_rays(loaded.K, loaded.c2w, loaded.height, loaded.width)
    expected = image_rays(views.K, views.c2w, views.height, views.width)
    for got, want in zip(rays, expected):
        torch.testing.assert_close(got, want, atol=1e-4, rtol=0)
    assert (scene.near, scene.far) == pytest.approx((1.8, 6.0))


def test_llff_recentring_and_scaling_is_one_similarity_transform(procedural_scene, tmp_path):
    views = procedural_scene.train.subset(list(range(16)))
    root = write_llff(views, tmp_path / "capture")
    scene = load_llff(root, downscale=2, holdout_every=4, bd_factor=0.75)
    # held out: views 0, 4, 8, 12; trained: the rest, in order
    assert scene.splits["val"].names == ["image000.png", "image004.png", "image008.png", "image012.png"]
    order = [i for i in range(16) if i % 4] + [0, 4, 8, 12]
    loaded = torch.cat([scene.train.c2w, scene.splits["val"].c2w]).double()
    original = views.c2w[order].double()
    # one rotation for every camera, and one scale: 1 / (nearest bound x 0.75) = 1 / 1.5
    rotation = loaded[:, :3, :3] @ original[:, :3, :3].transpose(1, 2)
    torch.testing.assert_close(rotation, rotation[:1].expand_as(rotation), atol=1e-5, rtol=0)
    distances = torch.cdist(loaded[:, :3, 3], loaded[:, :3, 3]) / torch.cdist(original[:, :3, 3], original[:, :3, 3]).clamp(min=1e-9)
    off_diagonal = ~torch.eye(16, dtype=torch.bool)
    torch.testing.assert_close(distances[off_diagonal], torch.full((16 * 15,), 1 / 1.5, dtype=torch.float64), atol=1e-5, rtol=0)
    # recentred: the mean camera centre is the origin and the cameras look down -z on average
    torch.testing.assert_close(loaded[:, :3, 3].mean(0), torch.zeros(3, dtype=torch.float64), atol=1e-5, rtol=0)
    mean_forward = torch.nn.functional.normalize(loaded[:, :3, 2].mean(0), dim=0)  # OpenCV +z: where a camera looks
    torch.testing.assert_close(mean_forward, torch.tensor([0.0, 0.0, -1.0], dtype=torch.float64), atol=1e-5, rtol=0)
    assert len(scene.splits["spiral"]) == 120 and scene.splits["spiral"].images is None
    # the kept similarity takes the file's cameras to the loaded ones
    mapped = apply_similarity(scene.world_from_capture.double(), original)
    torch.testing.assert_close(mapped, loaded, atol=1e-5, rtol=0)


def test_a_360_llff_capture_is_normalised_like_a_transforms_capture(procedural_scene, tmp_path):
    views = procedural_scene.train.subset(list(range(0, 80, 4)))  # 20 cameras all around the procedural subject
    root = write_llff(views, tmp_path / "capture")
    scene = load_llff(root, downscale=2, holdout_every=5, layout="360")
    loaded = torch.cat([scene.train.c2w, scene.splits["val"].c2w]).double()
    order = [i for i in range(20) if i % 5] + [0, 5, 10, 15]
    torch.testing.assert_close(apply_similarity(scene.world_from_capture.double(), views.c2w[order].double()), loaded, atol=1e-5, rtol=0)
    # the subject the cameras look at (the procedural origin) is the origin; the farthest camera coordinate is 1
    subject = scene.world_from_capture.double() @ torch.tensor([0.0, 0.0, 0.0, 1.0], dtype=torch.float64)
    torch.testing.assert_close(subject[:3], torch.zeros(3, dtype=torch.float64), atol=1e-3, rtol=0)
    assert float(loaded[:, :3, 3].abs().max()) == pytest.approx(1.0)
    assert scene.near == 0.05 and "spiral" not in scene.splits  # renders take the orbit of other 360 captures
    with pytest.raises(ValueError, match="forward-facing cameras"):
        SceneSpace.from_scene(scene, ndc=True)
    with pytest.raises(ValueError, match="data.scene.layout must be one of"):
        load_llff(root, downscale=2, layout="sideways")


def test_a_capture_with_only_full_size_images_gets_its_downscaled_folder_once(procedural_scene, tmp_path):
    views = procedural_scene.train.subset(list(range(6)))
    root = write_llff(views, tmp_path / "capture", downscale=1)  # images_1: rename it to the full-size images/
    (root / "images_1").rename(root / "images")
    scene = load_llff(root, downscale=2, holdout_every=0, bd_factor=None, recentre=False)
    assert (root / "images_2").is_dir() and len(list((root / "images_2").iterdir())) == 6
    assert scene.train.width == views.width // 2 and scene.train.K[0, 0, 0] == pytest.approx(float(views.K[0, 0, 0]) / 2)
    # each pixel the mean of its 2x2 block of the full-size image (uint8 rounding aside)
    full = views.images[0].float()
    block_mean = full.reshape(views.height // 2, 2, views.width // 2, 2, 3).mean((1, 3))
    assert (scene.train.images[0].float() - block_mean).abs().max() <= 1.0
    written = (root / "images_2").stat().st_mtime_ns
    load_llff(root, downscale=2, holdout_every=0, bd_factor=None, recentre=False)
    assert (root / "images_2").stat().st_mtime_ns == written  # read, not written again


def test_llff_bad_input_names_the_file(procedural_scene, tmp_path):
    views = procedural_scene.train.subset(list(range(4)))
    root = write_llff(views, tmp_path / "capture")
    with pytest.raises(FileNotFoundError, match=r"images_4 not found.*\['images_2'\]"):
        load_llff(root, downscale=4)
    (root / "images_2" / "image003.png").unlink()
    with pytest.raises(ValueError, match="3 images but .*poses_bounds.npy has 4 poses"):
        load_llff(root, downscale=2)
    np.save(root / "poses_bounds.npy", np.zeros((4, 15)))
    with pytest.raises(ValueError, match=r"poses_bounds.npy: expected an \(N, 17\) array"):
        load_llff(root, downscale=2)
    array = np.ones((4, 17))
    array[2, 3] = np.nan
    np.save(root / "poses_bounds.npy", array)
    with pytest.raises(ValueError, match="view 2 has non-finite values"):
        load_llff(root, downscale=2)


@pytest.mark.skipif(not (SHARED_DATA / "nerf_llff_data" / "fern").is_dir(), reason="fern is not in ../shared/data")
def test_fern_loads_like_the_nerf_code():
    scene = load_llff(SHARED_DATA / "nerf_llff_data" / "fern", downscale=8)
    train, val = scene.train, scene.splits["val"]
    assert (len(train), len(val)) == (17, 3) and (train.height, train.width) == (378, 504)
    assert float(train.K[0, 0, 0]) == pytest.approx(407.5658, abs=1e-3)  # the focal NeRF's load_llff prints for fern, factor 8
    forward = torch.nn.functional.normalize(train.c2w[:, :3, 2].mean(0), dim=0)
    assert forward[2] < -0.99  # forward-facing: the cameras look down -z of the recentred world
    assert scene.near == pytest.approx(1.2, abs=1e-6)  # 0.9 x the nearest bound, which the scaling made 1 / 0.75


def test_ndc_rays_pass_through_the_ndc_image_of_every_world_point_on_them():
    from nerf_lightning.geometry.rays import ndc_rays

    generator = torch.Generator().manual_seed(0)
    rays_o = torch.randn(50, 3, generator=generator, dtype=torch.float64) * 0.2
    rays_d = torch.nn.functional.normalize(torch.randn(50, 3, generator=generator, dtype=torch.float64) * 0.3 + torch.tensor([0, 0, -1.0]), dim=-1)
    focal, width, height = 400.0, 500, 380
    origins, directions = ndc_rays(rays_o, rays_d, focal, width, height, near_plane=1.0)
    for depth in (1.5, 5.0, 40.0):  # world points on the rays at these depths, beyond the near plane z = -1
        point = rays_o + ((-depth - rays_o[:, 2]) / rays_d[:, 2])[:, None] * rays_d
        x, y, z = point.unbind(-1)
        ndc_point = torch.stack([-2 * focal / width * x / z, -2 * focal / height * y / z, 1 + 2 * 1.0 / z], dim=-1)
        t = (ndc_point[:, 2] - origins[:, 2]) / directions[:, 2]
        assert ((t > 0) & (t < 1)).all()
        torch.testing.assert_close(origins + t[:, None] * directions, ndc_point)
    torch.testing.assert_close(origins[:, 2], torch.full((50,), -1.0, dtype=torch.float64))  # the near plane z = -1 maps to -1
    torch.testing.assert_close(origins[:, 2] + directions[:, 2], torch.ones(50, dtype=torch.float64))  # t = 1 is infinity


def test_a_forward_facing_capture_trains_in_ndc_and_renders_from_its_checkpoint(procedural_scene, tmp_path, monkeypatch, scene_cache):
    from nerf_lightning.checkpoints import load_model
    from nerf_lightning.config import compose_config
    from nerf_lightning.training import train

    train_views = procedural_scene.train
    root = write_forward_capture(procedural_scene, tmp_path)
    run = tmp_path / "run"
    metrics = train(compose_config([
        "experiment=fast_llff", f"data.root={root}", "data.scene.downscale=2", "data.scene.holdout_every=4",
        "model.field.aabb=[-3.2,-3.2,-1.0,3.2,3.2,1.0]",  # cameras 35 degrees apart see far past the average one's picture
        "model.field.encoding.n_levels=4", "model.field.encoding.log2_table_size=14", "model.field.encoding.max_resolution=128", "model.sampler.grid.resolution=16",
        "data.batch_size=256", "trainer.max_steps=20", "data.val_every=20", "trainer.enable_progress_bar=false",
        "trainer.enable_model_summary=false", f"paths.output_dir={run}",
    ]))
    assert metrics["step"] == 20 and np.isfinite(metrics["val/psnr"])
    model, _ = load_model(run / "checkpoints" / "last.ckpt")
    assert model.space.ndc.focal == pytest.approx(float(train_views.K[0, 0, 0])) and (model.space.near, model.space.far) == (0.0, 1.0)


def forward_capture(procedural_scene, tmp_path):
    """:func:`write_forward_capture`, loaded back."""
    return load_llff(write_forward_capture(procedural_scene, tmp_path), downscale=2, holdout_every=4)


def test_ndc_reach_is_the_farthest_any_training_ray_goes_in_x_and_y(procedural_scene, tmp_path):
    from nerf_lightning.geometry.space import ndc_reach

    scene = forward_capture(procedural_scene, tmp_path)
    space = SceneSpace.from_scene(scene, ndc=True)
    rays_o, rays_d = image_rays(scene.train.K, scene.train.c2w, scene.train.height, scene.train.width)
    origins, directions = space.ndc.rays(rays_o.reshape(-1, 3), rays_d.reshape(-1, 3))
    every_pixel = torch.cat([origins, origins + directions])[:, :2].abs().amax(dim=0)  # all pixels at both ends
    assert space.ndc.reach == pytest.approx(tuple(every_pixel.tolist()), rel=1e-5)
    assert space.ndc.reach == pytest.approx(ndc_reach(scene.train, space.ndc))
    assert max(space.ndc.reach) > 1.0  # the cameras see past the average camera's picture
    assert SceneSpace.from_state(space.state()).ndc.reach == pytest.approx(space.ndc.reach)  # kept in checkpoints


def test_an_ndc_box_that_cuts_off_the_training_rays_is_refused_with_the_box_to_set(procedural_scene, tmp_path):
    space = SceneSpace.from_scene(forward_capture(procedural_scene, tmp_path), ndc=True)
    with pytest.raises(ValueError, match=r"model.field.aabb is \[-1.0, -1.0, -1.0, 1.0, 1.0, 1.0\], but the training cameras' rays in NDC "
                                         r"\(data.ndc=true\) reach \|x\| = .* Set model.field.aabb=\[-.*, -1.0, .*\] or wider"):
        space.check_box(torch.tensor([-1.0, -1.0, -1.0, 1.0, 1.0, 1.0]), "model.field.aabb")
    x, y = (np.ceil(10 * value) / 10 for value in space.ndc.reach)
    space.check_box(torch.tensor([-x, -y, -1.0, x, y, 1.0]), "model.field.aabb")  # the box it names is enough
    state = space.state()
    del state["ndc"]["reach"]  # a checkpoint written before the reach was kept: nothing to check against
    SceneSpace.from_state(state).check_box(torch.tensor([-1.0, -1.0, -1.0, 1.0, 1.0, 1.0]), "model.field.aabb")
