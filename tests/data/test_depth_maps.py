"""A capture's depth maps (transforms.json's depth_file_path): read back into the scene's world, carried in the
batches, refused by name when bad; the depth loss of both models and what nerf-eval scores with it."""

import json

import numpy as np
import pytest
import torch

from nerf_lightning.data.formats import load_transforms
from nerf_lightning.data.formats.depth_capture import camera_z, phone_depth, write_depth_capture
from nerf_lightning.data.formats.depth_maps import write_depth_png
from nerf_lightning.data.images import downscale_depth
from nerf_lightning.data.scene import Scene
from nerf_lightning.geometry.cameras import pixel_ray_lengths
from nerf_lightning.metrics import depth_l1


@pytest.fixture(scope="module")
def small_scene(procedural_scene):
    """12 training and 2 held-out views of the procedural scene, with their true depth."""
    return Scene(splits={"train": procedural_scene.train.subset(list(range(12))), "val": procedural_scene.splits["val"].subset([0, 1])},
                 near=procedural_scene.near, far=procedural_scene.far, background=procedural_scene.background)


@pytest.mark.parametrize("suffix", [".png", ".npy"])
def test_depth_maps_read_back_the_true_depth_in_the_normalised_world(small_scene, tmp_path, suffix):
    path = write_depth_capture(small_scene, tmp_path / "capture", suffix=suffix)
    scene = load_transforms(path)
    scale = float(scene.world_from_capture[:3, :3].double().det().abs() ** (1.0 / 3.0))
    assert scale < 0.5  # cameras 4 units out, normalised to 1: the depth is scaled with them
    true, got = small_scene.train.depth.double() * scale, scene.train.depth.double()
    surface = torch.isfinite(true)
    assert torch.isnan(got[~surface]).all()  # no reading (0 in the file): unknown, not "nothing there"
    # a PNG holds whole millimetres: half of one, scaled and along the slanted ray (at most 1.3 times camera z here)
    tolerance = 0.5e-3 * scale * 1.3 + 1e-6 if suffix == ".png" else 1e-5
    assert float((got[surface] - true[surface]).abs().max()) <= tolerance
    torch.testing.assert_close(scene.splits["val"].depth[torch.isfinite(scene.splits["val"].depth)],
                               (small_scene.splits["val"].depth.double() * scale)[torch.isfinite(small_scene.splits["val"].depth)].float(),
                               atol=tolerance, rtol=0)


def test_a_phone_style_depth_map_a_quarter_the_size_is_upsampled_and_downscaled_with_the_photos(small_scene, tmp_path):
    path = write_depth_capture(small_scene, tmp_path / "capture", shrink=4, noise=0.02)
    scene = load_transforms(path, normalise=False, downscale=2, holdout_every=0)
    depth = scene.train.depth
    assert depth.shape == (12, 50, 50)
    true = downscale_depth(small_scene.train.depth[0].double(), 2)
    known = torch.isfinite(depth[0]) & torch.isfinite(true)
    assert known.float().mean() > 0.1
    relative = ((depth[0].double() - true)[known].abs() / true[known])
    assert float(relative.median()) < 0.05  # 2% noise, and the blocks' means at the objects' edges


def test_camera_z_and_phone_depth():
    K = torch.tensor([[50.0, 0.0, 20.0], [0.0, 50.0, 20.0], [0.0, 0.0, 1.0]])
    z = torch.full((40, 40), 3.0, dtype=torch.float64)
    z[:4, :4] = float("inf")
    views = type("V", (), {"K": K[None], "height": 40, "width": 40, "depth": (z * pixel_ray_lengths(K.double(), 40, 40))[None]})
    torch.testing.assert_close(camera_z(views)[0], z)
    small = phone_depth(z, shrink=4)
    assert small.shape == (10, 10) and small[0, 0] == 0 and float(small[1:, 1:].max()) == 3.0


def test_depth_l1_covers_the_known_pixels_alone():
    depth = torch.tensor([1.0, 2.0, 3.0, 4.0], requires_grad=True)
    target = torch.tensor([1.5, float("nan"), float("inf"), 0.0])
    loss = depth_l1(depth, target)
    assert float(loss.detach()) == pytest.approx(0.5)
    loss.backward()
    assert depth.grad.tolist() == [-1.0, 0.0, 0.0, 0.0]
    depth = depth.detach()
    assert float(depth_l1(depth, torch.full((4,), float("nan")))) == 0.0
    assert float(depth_l1(depth, torch.tensor([1.5, 3.0, 1.0, 1.0]), torch.tensor([1.0, 0.0, 0.0, 0.0]))) == pytest.approx(0.5)


def _frames(path):
    return json.loads(path.read_text())


def test_bad_depth_maps_are_refused_naming_the_file(small_scene, tmp_path):
    path = write_depth_capture(small_scene, tmp_path / "capture", splits=("train",))
    meta = _frames(path)
    depth_file = path.parent / meta["frames"][2]["depth_file_path"]

    def load_with(change):
        changed = json.loads(json.dumps(meta))
        change(changed)
        path.write_text(json.dumps(changed))
        return load_transforms(path, holdout_every=0)

    depth_file.unlink()
    with pytest.raises(FileNotFoundError, match="depth map file not found: .*train_002.png"):
        load_with(lambda m: None)
    depth_file.write_bytes(b"not a png")
    with pytest.raises(ValueError, match="could not read depth map .*train_002.png"):
        load_with(lambda m: None)
    write_depth_png(depth_file, np.ones((30, 20)))
    with pytest.raises(ValueError, match="depth map .*train_002.png is 20x30, not the shape of its 100x100 photo"):
        load_with(lambda m: None)
    np.save(depth_file.with_suffix(".npy"), np.ones((100, 100, 3)))
    with pytest.raises(ValueError, match="train_002.npy has shape \\(100, 100, 3\\)"):
        load_with(lambda m: m["frames"][2].update(depth_file_path="depth/train_002.npy"))
    with pytest.raises(ValueError, match="11 frames have a 'depth_file_path' but 1 do not"):
        load_with(lambda m: m["frames"][2].pop("depth_file_path"))
    with pytest.raises(ValueError, match="'depth_unit_scale_factor' must be a number > 0"):
        load_with(lambda m: m.update(depth_unit_scale_factor="mm"))


def test_the_jsons_depth_unit_scale_factor_replaces_the_files_unit(small_scene, tmp_path):
    path = write_depth_capture(small_scene, tmp_path / "capture", suffix=".npy", splits=("train",))
    metres = load_transforms(path, normalise=False, holdout_every=0).train.depth
    meta = json.loads(path.read_text())
    for frame in meta["frames"]:  # the same maps in millimetres, as nerfstudio's .npy files may be
        np.save(path.parent / frame["depth_file_path"], np.load(path.parent / frame["depth_file_path"]) * 1000.0)
    path.write_text(json.dumps({**meta, "depth_unit_scale_factor": 0.001}))
    millimetres = load_transforms(path, normalise=False, holdout_every=0).train.depth
    torch.testing.assert_close(millimetres, metres, equal_nan=True)


def test_depth_maps_of_a_distorted_capture_are_undistorted_with_their_photos(small_scene, tmp_path):
    path = write_depth_capture(small_scene, tmp_path / "capture", splits=("train",))
    meta = json.loads(path.read_text())
    path.write_text(json.dumps({**meta, "k1": 0.02}))
    depth = load_transforms(path, normalise=False, holdout_every=0).train.depth
    true = small_scene.train.depth
    known = torch.isfinite(depth)
    assert depth.shape == true.shape and bool(known.any()) and bool((depth[known] > 0).all())
    # a slight distortion moves the surfaces by under a pixel or two: the known depths are the surfaces' depths
    assert float(((depth - true)[known & torch.isfinite(true)]).abs().median()) < 0.05


def test_a_coarse_views_depth_is_each_blocks_mean_of_its_known_values():
    from nerf_lightning.data.views import coarse_view

    depth = torch.tensor([[1.0, 3.0, float("nan"), float("nan")], [1.0, 3.0, float("nan"), 4.0]])
    drawn = {"image": torch.zeros(2, 4, 3), "K": torch.eye(3), "depth": depth, "height": 2, "width": 4}
    coarse = coarse_view(drawn, 2)
    assert coarse["depth"].tolist() == [[2.0, 4.0]]
    assert torch.isnan(downscale_depth(torch.full((2, 2), float("nan")), 2)).all()
