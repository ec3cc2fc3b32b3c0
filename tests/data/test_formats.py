"""Loaders: the procedural scene's true geometry checks the whole chain file -> Scene -> rays."""

import json
import math
import shutil

import numpy as np
import pytest
import torch

from nerf_lightning.data.formats import load_blender, load_npz, load_procedural, save_npz
from nerf_lightning.data.formats.procedural import surface_distance
from nerf_lightning.data.scene import Views
from nerf_lightning.geometry import image_rays
from tests.conftest import SHARED_DATA

LEGO = SHARED_DATA / "nerf_synthetic" / "lego"


def surface_points(views: Views, depth: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Points at the given per-pixel ray depth (V, H, W), and whether a surface was hit there."""
    rays_o, rays_d = image_rays(views.K.double(), views.c2w.double(), views.height, views.width)
    t = depth.reshape(len(views), -1).double()
    hit = torch.isfinite(t)
    return rays_o + rays_d * t.nan_to_num(posinf=0.0)[..., None], hit


def test_procedural_scene_depth_lies_on_the_analytic_surface(procedural_scene):
    assert {name: len(views) for name, views in procedural_scene.splits.items()} == {"train": 80, "val": 10, "test": 10}
    for split in ("train", "test"):
        views = procedural_scene.splits[split]
        points, hit = surface_points(views, views.depth)
        assert hit.float().mean() > 0.15  # the objects fill a good part of each view
        assert surface_distance(points[hit]).abs().max() < 1e-3
        # pixels without a surface are the white background, kept as uint8
        assert views.images.dtype == torch.uint8
        rgb = views.images.reshape(len(views), -1, 3)
        assert (rgb[~hit] == 255).all()


def test_procedural_scene_is_deterministic_and_cached(procedural_scene, scene_cache, tmp_path):
    again = load_procedural(cache_dir=scene_cache)  # from the cache
    assert torch.equal(again.train.images, procedural_scene.train.images)
    fresh = load_procedural(cache_dir=tmp_path)  # rendered anew
    assert torch.equal(fresh.train.images, procedural_scene.train.images)
    assert torch.equal(fresh.train.c2w, procedural_scene.train.c2w)


def test_procedural_highlight_depends_on_the_view(procedural_scene):
    from nerf_lightning.data.formats.procedural import shade

    hit = {"normal": torch.tensor([[0.0, 0.0, 1.0]] * 2, dtype=torch.float64), "albedo": torch.full((2, 3), 0.5, dtype=torch.float64)}
    mirror = torch.nn.functional.normalize(torch.tensor([-0.4, 0.3, 0.85], dtype=torch.float64), dim=0)
    views = torch.stack([-mirror, torch.tensor([0.0, 0.8, -0.6], dtype=torch.float64)])  # into the highlight, and away
    colours = shade(hit, views)
    assert (colours[0] - colours[1]).min() > 0.3


@pytest.mark.parametrize("convention", ["opencv", "opengl"])
def test_npz_round_trip_and_its_convention(procedural_scene, tmp_path, convention):
    path = save_npz(procedural_scene, tmp_path / "scene.npz", convention=convention)
    scene = load_npz(path)  # convention=auto
    torch.testing.assert_close(scene.train.c2w, procedural_scene.train.c2w)
    torch.testing.assert_close(scene.train.K, procedural_scene.train.K)
    assert torch.equal(scene.train.images, procedural_scene.train.images)  # uint8 both ways
    # the rays of the loaded cameras meet the true surface at the true depth
    points, hit = surface_points(scene.train.subset([0, 1, 2]), procedural_scene.train.depth[:3])
    assert surface_distance(points[hit]).abs().max() < 1e-3
    assert set(scene.splits) == {"train", "val", "test", "render"} and scene.splits["render"].images is None


def test_npz_wrong_convention_is_refused(procedural_scene, tmp_path):
    path = save_npz(procedural_scene, tmp_path / "scene.npz", convention="opencv")
    with pytest.raises(ValueError, match="do not look at a common point in the opengl convention"):
        load_npz(path, convention="opengl")


def test_npz_bad_files_name_the_key(procedural_scene, tmp_path):
    path = save_npz(procedural_scene, tmp_path / "scene.npz")
    data = dict(np.load(path))
    np.savez(tmp_path / "missing.npz", **{k: v for k, v in data.items() if k != "c2ws_val"})
    with pytest.raises(ValueError, match=r"missing.npz: missing key\(s\) \['c2ws_val'\]"):
        load_npz(tmp_path / "missing.npz")
    np.savez(tmp_path / "counts.npz", **{**data, "c2ws_train": data["c2ws_train"][:-1]})
    with pytest.raises(ValueError, match="'images_train' has 80 images but 'c2ws_train' 79 cameras"):
        load_npz(tmp_path / "counts.npz")
    bad = data["c2ws_test"].copy()
    bad[2, 1, 3] = np.inf
    np.savez(tmp_path / "inf.npz", **{**data, "c2ws_test": bad})
    with pytest.raises(ValueError, match="'c2ws_test': camera 2 has non-finite"):
        load_npz(tmp_path / "inf.npz")
    with pytest.raises(FileNotFoundError, match="nope.npz"):
        load_npz(tmp_path / "nope.npz")


def copy_procedural(scene_cache, tmp_path):
    """A copy of the default procedural scene (100 views of 100 px) of the session's cache, as a Blender folder; other
    tests cache smaller ones beside it."""
    from nerf_lightning.data.formats.procedural import load_procedural

    load_procedural(cache_dir=scene_cache)  # made once a session
    (source,) = [p for p in scene_cache.iterdir() if p.name.startswith("procedural_") and p.name.endswith("_100views_100px")]
    return shutil.copytree(source, tmp_path / "scene")


def test_blender_options(procedural_scene, scene_cache, tmp_path):
    root = copy_procedural(scene_cache, tmp_path)
    half = load_blender(root, downscale=2, max_views=8, holdout_every=4)
    assert len(half.train) == 6 and len(half.splits["val"]) == 2 and len(half.splits["test"]) == 8
    assert (half.train.height, half.train.width) == (50, 50)
    torch.testing.assert_close(half.train.K[0, 0, 0], procedural_scene.train.K[0, 0, 0] / 2)
    assert half.train.depth is None  # true depth is kept at full size only
    black = load_blender(root, background=(0.0, 0.0, 0.0), max_views=3)
    assert black.train.images[0, 0, 0].tolist() == [0, 0, 0]


def test_blender_bad_input_names_file_and_key(scene_cache, tmp_path):
    root = copy_procedural(scene_cache, tmp_path)
    with pytest.raises(FileNotFoundError, match="folder not found"):
        load_blender(tmp_path / "nothing")
    meta = json.loads((root / "transforms_train.json").read_text())

    (root / "transforms_train.json").write_text(json.dumps({"camera_angle_x": 0.5}))
    with pytest.raises(ValueError, match="transforms_train.json: missing key 'frames'"):
        load_blender(root)
    del meta["frames"][3]["transform_matrix"]
    (root / "transforms_train.json").write_text(json.dumps(meta))
    with pytest.raises(ValueError, match="transforms_train.json: frame 3: missing key 'transform_matrix'"):
        load_blender(root)
    meta = json.loads((root / "transforms_val.json").read_text())
    (root / "transforms_train.json").write_text(json.dumps(meta))
    (root / meta["frames"][1]["file_path"]).with_suffix(".png").write_bytes(b"not a png")
    with pytest.raises(ValueError, match=r"could not read image .*r_13.png"):
        load_blender(root)
    (root / meta["frames"][1]["file_path"]).with_suffix(".png").unlink()
    with pytest.raises(FileNotFoundError, match=r"r_13.png"):
        load_blender(root)


@pytest.mark.skipif(not LEGO.is_dir(), reason="lego is not in ../shared/data")
def test_lego_at_200x200():
    scene = load_blender(LEGO, downscale=4, max_views=5)
    assert (scene.train.height, scene.train.width) == (200, 200)
    focal = 0.5 * 800 / math.tan(0.5 * 0.6911112070083618) / 4
    assert scene.train.K[0, 0, 0].item() == pytest.approx(focal, rel=1e-5)
    assert scene.train.K[0, 0, 2].item() == 100.0
    assert (scene.train.images[:, 0, 0] == 255).all()  # corners: background, composited white
    assert scene.splits["test"] is scene.splits["val"]  # lego here has no test split
    radius = scene.train.c2w[:, :3, 3].norm(dim=-1)
    torch.testing.assert_close(radius, torch.full_like(radius, 4.031), atol=0.01, rtol=0)
