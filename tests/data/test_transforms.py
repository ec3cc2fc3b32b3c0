"""transforms.json (instant-ngp / nerfstudio): round trip, missing frames, normalisation kept, distortion undone."""

import json
import logging

import kornia
import pytest
import torch

from nerf_lightning.data.formats import load_transforms
from nerf_lightning.data.formats.shared import apply_similarity
from nerf_lightning.data.image_stack import as_float_rgb
from nerf_lightning.geometry.cameras import opengl_to_opencv
from nerf_lightning.geometry.paths import look_at_point
from nerf_lightning.geometry.rays import image_rays
from nerf_lightning.io import write_png
from tests.conftest import SHARED_DATA


def write_transforms(views, root, extra_frames=(), images=None, distortion=None, per_frame=None):
    """The views as a transforms.json capture (global intrinsics of view 0; ``per_frame`` {index: keys} overrides)."""
    (root / "images").mkdir(parents=True)
    K = views.K[0]
    meta = {"fl_x": float(K[0, 0]), "fl_y": float(K[1, 1]), "cx": float(K[0, 2]), "cy": float(K[1, 2]),
            "w": views.width, "h": views.height, "aabb_scale": 2, "frames": []}
    if distortion is not None:
        meta.update(dict(zip(("k1", "k2", "p1", "p2"), distortion)))
    for index, image in enumerate(views.images if images is None else images):
        write_png(root / "images" / f"{index:04d}.png", image)
        frame = {"file_path": f"images/{index:04d}.png", "transform_matrix": opengl_to_opencv(views.c2w[index]).tolist()}
        frame.update((per_frame or {}).get(index, {}))
        meta["frames"].append(frame)
    meta["frames"] += list(extra_frames)
    (root / "transforms.json").write_text(json.dumps(meta))
    return root


def test_transforms_round_trip_skips_missing_frames_with_one_warning(procedural_scene, tmp_path, caplog):
    views = procedural_scene.train.subset(list(range(10)))
    views.K[3, 0, 0] += 7.0  # frame 3 declares its own focal length
    missing = [{"file_path": "images/gone_a.png", "transform_matrix": torch.eye(4).tolist()},
               {"file_path": "images/gone_b.png", "transform_matrix": torch.eye(4).tolist()}]
    root = write_transforms(views, tmp_path / "capture", missing, per_frame={3: {"fl_x": float(views.K[3, 0, 0])}})
    with caplog.at_level(logging.WARNING):
        scene = load_transforms(root, holdout_every=0, normalise=False)
    warnings = [r.getMessage() for r in caplog.records if r.levelno == logging.WARNING]
    assert len(warnings) == 1 and "2 of 12 frames have no image file" in warnings[0] and "gone_a.png, images/gone_b.png" in warnings[0]
    loaded = scene.train
    assert len(loaded) == 10 and scene.aabb_scale == 2
    torch.testing.assert_close(loaded.K, views.K)
    torch.testing.assert_close(loaded.c2w, views.c2w, atol=1e-5, rtol=0)
    assert torch.equal(loaded.images, views.images)  # uint8, through 8-bit PNG
    for got, want in zip(image_rays(loaded.K, loaded.c2w, 100, 100), image_rays(views.K, views.c2w, 100, 100)):
        torch.testing.assert_close(got, want, atol=1e-4, rtol=0)


@pytest.mark.parametrize("centre", ["poses", "focus"])
def test_transforms_normalisation_is_kept_to_map_back(procedural_scene, tmp_path, centre):
    views = procedural_scene.train.subset(list(range(16)))
    views.c2w[:, :3, 3] += torch.tensor([3.0, -2.0, 1.0])  # the subject away from the file's origin
    root = write_transforms(views, tmp_path / "capture")
    scene = load_transforms(root, holdout_every=4, centre=centre)
    assert len(scene.train) == 12 and len(scene.splits["val"]) == 4
    order = [i for i in range(16) if i % 4] + [0, 4, 8, 12]
    loaded = torch.cat([scene.train.c2w, scene.splits["val"].c2w])
    centres = loaded[:, :3, 3]
    # poses: the mean camera centre at the origin; focus: the point the cameras look at (the procedural scene's centre)
    origin = centres.mean(0) if centre == "poses" else look_at_point(loaded)
    torch.testing.assert_close(origin, torch.zeros(3), atol=1e-5, rtol=0)
    if centre == "focus":
        assert float(centres.mean(0).norm()) > 0.05  # 16 cameras of a sphere: their mean is not its centre
    assert float(centres.abs().max()) == pytest.approx(1.0, abs=1e-5)
    up = torch.nn.functional.normalize(-loaded[:, :3, 1].mean(0), dim=0)  # OpenCV: -y is up
    torch.testing.assert_close(up, torch.tensor([0.0, 0.0, 1.0]), atol=1e-5, rtol=0)
    # the kept transform takes the file's cameras to the loaded ones
    mapped = opengl_to_opencv(apply_similarity(scene.world_from_capture.double(), opengl_to_opencv(views.c2w[order]).double())).float()
    torch.testing.assert_close(mapped, loaded, atol=1e-5, rtol=0)


def test_transforms_undistorts_a_distorted_capture(procedural_scene, tmp_path):
    views = procedural_scene.train.subset([5])
    # smoothed, so that resampling it twice costs little and what remains measures where the pixels went
    clean = kornia.filters.gaussian_blur2d(as_float_rgb(views.images[0]).permute(2, 0, 1)[None], (9, 9), (2.0, 2.0))[0].permute(1, 2, 0)
    K = views.K[0]
    distortion = torch.tensor([0.4, -0.1, 0.004, -0.002])  # up to about 4 pixels at the corners of this 50-degree view
    # the image a lens with this distortion takes: each of its pixels sees the clean image at its undistorted point
    pixels = kornia.utils.create_meshgrid(100, 100, normalized_coordinates=False).reshape(1, -1, 2)
    ideal = kornia.geometry.calibration.undistort_points(pixels, K[None], distortion[None])
    grid = (ideal / 99.0 * 2.0 - 1.0).reshape(1, 100, 100, 2)
    distorted = torch.nn.functional.grid_sample(clean.permute(2, 0, 1)[None], grid, align_corners=True)[0].permute(1, 2, 0)
    root = write_transforms(views, tmp_path / "capture", images=[distorted], distortion=distortion.tolist())
    loaded = as_float_rgb(load_transforms(root, holdout_every=0, normalise=False).train.images[0])
    inner = (slice(12, -12), slice(12, -12))
    error_before = (distorted[inner] - clean[inner]).abs().mean()
    error_after = (loaded[inner] - clean[inner]).abs().mean()
    assert error_before > 0.008  # the distortion is visible (0.013 here)
    assert error_after < 0.25 * error_before  # and undone, up to two bilinear resamplings and 8-bit PNG (0.0017 here)


def test_transforms_bad_input_names_the_file_and_key(procedural_scene, tmp_path):
    views = procedural_scene.train.subset([0, 1])
    root = write_transforms(views, tmp_path / "capture")
    meta = json.loads((root / "transforms.json").read_text())
    del meta["frames"][1]["transform_matrix"]
    (root / "transforms.json").write_text(json.dumps(meta))
    with pytest.raises(ValueError, match=r"transforms.json: frame 1: missing key 'transform_matrix'"):
        load_transforms(root)
    meta = json.loads((root / "transforms.json").read_text())
    meta["frames"][1]["transform_matrix"] = meta["frames"][0]["transform_matrix"]
    for key in ("fl_x", "fl_y"):
        del meta[key]
    (root / "transforms.json").write_text(json.dumps(meta))
    with pytest.raises(ValueError, match="frame 0 .*no focal length"):
        load_transforms(root)
    meta["fl_x"], meta["w"] = 100.0, 640
    (root / "transforms.json").write_text(json.dumps(meta))
    with pytest.raises(ValueError, match="'w' is 640 but the image is 100x100"):
        load_transforms(root)
    with pytest.raises(FileNotFoundError, match="transforms.json not found"):
        load_transforms(tmp_path / "nowhere")


@pytest.mark.skipif(not (SHARED_DATA / "nerfstudio" / "fox").is_dir(), reason="fox is not in ../shared/data")
def test_fox_loads_its_50_images_of_67_frames(caplog):
    with caplog.at_level(logging.WARNING):
        scene = load_transforms(SHARED_DATA / "nerfstudio" / "fox", downscale=8)
    assert any("17 of 67 frames have no image file" in r.getMessage() for r in caplog.records)
    assert len(scene.train) + len(scene.splits["val"]) == 50 and (scene.train.height, scene.train.width) == (240, 135)
    assert float(scene.train.K[0, 0, 0]) == pytest.approx(1375.52 / 8) and scene.aabb_scale == 4


def test_nerfstudio_split_filenames_choose_the_splits(procedural_scene, tmp_path, caplog):
    views = procedural_scene.train.subset(list(range(6)))
    root = write_transforms(views, tmp_path / "capture")
    meta = json.loads((root / "transforms.json").read_text())
    meta.update(train_filenames=["images/0000.png", "./images/0002.png", "images/0004.png", "images/0005.png"],
                val_filenames=["images/0001.png", "images/gone.png"], test_filenames=["images/0003.png"])
    (root / "transforms.json").write_text(json.dumps(meta))
    with caplog.at_level(logging.WARNING):
        scene = load_transforms(root, holdout_every=2, normalise=False)  # the named splits win over holdout_every
    assert scene.train.names == ["0000.png", "0002.png", "0004.png", "0005.png"]
    assert scene.splits["val"].names == ["0001.png"] and scene.splits["test"].names == ["0003.png"]
    assert any("1 of the 2 'val_filenames' have no frame with an image" in r.getMessage() for r in caplog.records)
    torch.testing.assert_close(scene.splits["test"].c2w, views.c2w[3:4], atol=1e-5, rtol=0)
