"""The turntable capture: its masks, its object-frame poses and its room-frame cameras are exact, and it loads."""

import json
import math
from pathlib import Path

import imageio.v3 as iio
import numpy as np
import pytest
import torch

from nerf_lightning.data.formats.transforms import load_transforms
from nerf_lightning.data.formats.turntable import (
    BOXES, SPHERES, VERSION, load_turntable, make_turntable_capture, trace_object, trace_room, turn_about_z,
)
from nerf_lightning.geometry.cameras import opengl_to_opencv, pixel_to_ray

N_PHOTOS, SIZE = 8, 40  # two rings of four photos: enough to check, quick to render


@pytest.fixture(scope="module")
def capture(tmp_path_factory) -> Path:
    return make_turntable_capture(tmp_path_factory.mktemp("turntable") / "capture", n_photos=N_PHOTOS, size=SIZE)


def metadata(root: Path) -> tuple[dict, dict]:
    return json.loads((root / "transforms.json").read_text()), json.loads((root / "turntable.json").read_text())


def intrinsics(meta: dict) -> torch.Tensor:
    return torch.tensor([[meta["fl_x"], 0.0, meta["cx"]], [0.0, meta["fl_y"], meta["cy"]], [0.0, 0.0, 1.0]], dtype=torch.float64)


def test_the_same_arguments_give_the_same_bytes(capture, tmp_path):
    again = make_turntable_capture(tmp_path / "again", n_photos=N_PHOTOS, size=SIZE)
    files = sorted(path.relative_to(capture) for path in capture.rglob("*") if path.is_file())
    assert files == sorted(path.relative_to(again) for path in again.rglob("*") if path.is_file())
    assert len(files) == 2 * N_PHOTOS + 2
    for name in files:
        assert (capture / name).read_bytes() == (again / name).read_bytes(), name


def test_photos_are_rgb_and_masks_are_8_bit_object_silhouettes(capture):
    meta, turntable = metadata(capture)
    assert (meta["w"], meta["h"], meta["cx"], meta["cy"]) == (SIZE, SIZE, SIZE / 2, SIZE / 2)
    assert meta["fl_x"] == pytest.approx(0.5 * SIZE / math.tan(math.radians(45.0) / 2))
    assert turntable["version"] == VERSION and len(turntable["photos"]) == N_PHOTOS
    for index, frame in enumerate(meta["frames"]):
        assert frame["file_path"] == f"images/turn_{index:03d}.png" and frame["mask_path"] == f"masks/turn_{index:03d}.png"
        photo, mask = iio.imread(capture / frame["file_path"]), iio.imread(capture / frame["mask_path"])
        assert photo.shape == (SIZE, SIZE, 3) and photo.dtype == np.uint8  # RGB, no alpha: the room shows
        assert mask.shape == (SIZE, SIZE) and mask.dtype == np.uint8 and set(np.unique(mask)) == {0, 255}
        assert 0.1 < (mask == 255).mean() < 0.5  # the object fills a good part of the frame, the room the rest


def test_a_mask_marks_the_pixels_whose_samples_mostly_hit_the_object_first(capture):
    meta, turntable = metadata(capture)
    K = intrinsics(meta)
    rows, columns = torch.meshgrid(torch.arange(SIZE), torch.arange(SIZE), indexing="ij")
    offsets = torch.tensor([[0.25, 0.25], [0.75, 0.25], [0.25, 0.75], [0.75, 0.75]], dtype=torch.float64)
    uv = (torch.stack([columns, rows], -1).reshape(-1, 1, 2).double() + offsets).reshape(-1, 2)  # (H W 4, 2) the 2x2 samples
    for frame, photo in zip(meta["frames"], turntable["photos"]):
        # the object traced in its own frame from transform_matrix, the room in its frame from the room's camera
        object_c2w = opengl_to_opencv(torch.tensor(frame["transform_matrix"], dtype=torch.float64))
        room_c2w = opengl_to_opencv(torch.tensor(photo["room_transform_matrix"], dtype=torch.float64))
        t_object = trace_object(*pixel_to_ray(K, object_c2w, uv))[0]
        t_room = trace_room(*pixel_to_ray(K, room_c2w, uv))[0]
        covered = (t_object < t_room).reshape(SIZE, SIZE, 4).sum(-1) >= 2
        mask = torch.from_numpy(iio.imread(capture / frame["mask_path"])) == 255
        assert torch.equal(covered, mask), frame["mask_path"]


def test_the_object_frame_poses_put_the_object_where_the_photos_show_it(capture):
    meta, _ = metadata(capture)
    K = intrinsics(meta)
    # the centres of the object's spheres and boxes: inside it, so every photo shows the object there
    inside = torch.tensor([centre for centre, _ in SPHERES + BOXES], dtype=torch.float64)
    for frame in meta["frames"]:
        w2c = torch.linalg.inv(opengl_to_opencv(torch.tensor(frame["transform_matrix"], dtype=torch.float64)))
        camera = inside @ w2c[:3, :3].T + w2c[:3, 3]
        u, v = (camera @ K.T)[:, :2].div(camera[:, 2:]).floor().long().T
        mask = iio.imread(capture / frame["mask_path"])
        assert (mask[v.numpy(), u.numpy()] == 255).all(), frame["file_path"]


def test_within_a_ring_the_camera_stands_still_in_the_room_and_circles_the_object(capture):
    meta, turntable = metadata(capture)
    per_ring = N_PHOTOS // 2
    turns = torch.tensor([photo["turn_degrees"] for photo in turntable["photos"]], dtype=torch.float64)
    room = torch.tensor([photo["room_transform_matrix"] for photo in turntable["photos"]], dtype=torch.float64)
    objects = torch.tensor([frame["transform_matrix"] for frame in meta["frames"]], dtype=torch.float64)
    assert [photo["ring"] for photo in turntable["photos"]] == [0] * per_ring + [1] * per_ring
    # the room's camera turned by -turn about the axis is the object's camera
    assert torch.allclose(turn_about_z(torch.deg2rad(-turns)) @ room, objects, atol=1e-12)
    for ring in range(2):
        photos = slice(ring * per_ring, (ring + 1) * per_ring)
        assert torch.equal(room[photos], room[photos][:1].expand(per_ring, 4, 4))
        assert torch.allclose(turns[photos].diff(), torch.full((per_ring - 1,), 360.0 / per_ring, dtype=torch.float64))
        centres = objects[photos, :3, 3]
        assert torch.allclose(centres[:, :2].norm(dim=-1), centres[0, :2].norm().expand(per_ring))  # one circle about the axis
        assert torch.allclose(centres[:, 2], centres[0, 2].expand(per_ring))
        azimuth = torch.rad2deg(torch.atan2(centres[:, 1], centres[:, 0]))
        assert torch.allclose((azimuth.diff() + 360.0) % 360.0, torch.full((per_ring - 1,), 360.0 - 360.0 / per_ring, dtype=torch.float64))
    assert room[0, 2, 3] < room[per_ring, 2, 3]  # the second ring is higher
    assert turns[per_ring] - turns[0] == pytest.approx(360.0 / per_ring / 2)  # and its turns fall between the first's


def test_the_capture_loads_with_the_transforms_loader(capture):
    meta, _ = metadata(capture)
    scene = load_transforms(capture, holdout_every=4)
    assert sorted(scene.train.names + scene.splits["val"].names) == [f"turn_{index:03d}.png" for index in range(N_PHOTOS)]
    assert scene.splits["val"].names == ["turn_000.png", "turn_004.png"]
    views = scene.train
    assert (views.height, views.width) == (SIZE, SIZE) and views.images.shape[1:] == (SIZE, SIZE, 3)
    assert torch.allclose(views.K[0].double(), intrinsics(meta), atol=1e-4)
    masks = getattr(views, "masks", None)
    if masks is not None:  # the loader reads frames' mask_path
        expected = torch.stack([torch.from_numpy(iio.imread(capture / "masks" / name)) == 255 for name in views.names])
        assert torch.equal(masks.cpu().bool(), expected)


def test_load_turntable_renders_once_into_its_cache(tmp_path, monkeypatch):
    scene = load_turntable(n_photos=4, size=16, cache_dir=tmp_path, holdout_every=0)
    assert [path.name for path in tmp_path.iterdir()] == [f"turntable_v{VERSION}_4photos_16px"]
    assert len(scene.train) == 4 and scene.train.images.shape[1:] == (16, 16, 3)
    monkeypatch.setattr("nerf_lightning.data.formats.turntable.make_turntable_capture", lambda *args, **kwargs: pytest.fail("rendered again"))
    again = load_turntable(n_photos=4, size=16, cache_dir=tmp_path, holdout_every=0)
    assert torch.equal(again.train.images, scene.train.images)


def test_photos_must_split_evenly_into_rings(tmp_path):
    with pytest.raises(ValueError, match="multiple of rings"):
        make_turntable_capture(tmp_path, n_photos=7, size=8, rings=2)
