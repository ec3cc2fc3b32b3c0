"""Sparse points: a transforms.json's ply_file_path (what nerf-process-data writes) and an LLFF capture's COLMAP
model load into the scene's world, where the loaded cameras see them at the pixels the capture's cameras did."""

import json
import struct

import numpy as np
import pytest
import torch

from nerf_lightning.capture.output import write_points_ply
from nerf_lightning.data.formats import load_llff, load_transforms
from nerf_lightning.data.points import read_colmap_points
from nerf_lightning.geometry import pinhole_camera
from tests.data.test_llff import write_llff
from tests.data.test_transforms import write_transforms


def surface_points(views, count=300):
    """(count, 3) float64 points on the surfaces the views see, with (count, 3) uint8 colours."""
    points = views.subset([0]).surface_points()
    chosen = torch.randperm(len(points), generator=torch.Generator().manual_seed(0))[:count]
    colours = torch.randint(0, 256, (count, 3), generator=torch.Generator().manual_seed(1), dtype=torch.uint8)
    return points[chosen].numpy(), colours.numpy()


def assert_seen_at_the_same_pixels(points, positions, capture_views, loaded_views):
    """The capture's cameras see ``points`` (its coordinates) where the loaded cameras see ``positions`` (the scene's)."""
    original = pinhole_camera(capture_views.K[:1].double(), capture_views.c2w[:1].double(), capture_views.height, capture_views.width)
    loaded = pinhole_camera(loaded_views.K[:1].double(), loaded_views.c2w[:1].double(), loaded_views.height, loaded_views.width)
    torch.testing.assert_close(loaded.project(positions.double()[None])[0], original.project(torch.from_numpy(points)[None])[0], atol=1e-3, rtol=0)


def test_a_transforms_capture_brings_its_ply_points_into_the_normalised_world(procedural_scene, tmp_path):
    views = procedural_scene.train.subset(list(range(8)))
    root = write_transforms(views, tmp_path / "capture")
    points, colours = surface_points(views)
    write_points_ply(root / "sparse_pc.ply", points, colours)  # as nerf-process-data writes it
    meta = json.loads((root / "transforms.json").read_text())
    (root / "transforms.json").write_text(json.dumps({**meta, "ply_file_path": "sparse_pc.ply"}))

    scene = load_transforms(root, holdout_every=0)
    assert scene.points is not None and len(scene.points) == 300
    assert scene.points.positions.dtype == torch.float32 and scene.points.colours.dtype == torch.uint8
    assert torch.equal(scene.points.colours, torch.from_numpy(colours))
    transform = scene.world_from_capture.double()
    torch.testing.assert_close(scene.points.positions.double(), torch.from_numpy(points) @ transform[:3, :3].T + transform[:3, 3], atol=1e-5, rtol=0)
    assert scene.points.positions.abs().max() < 1.0  # the subject, inside the cameras' unit box
    assert_seen_at_the_same_pixels(points, scene.points.positions, views, scene.train)
    assert load_transforms(root, holdout_every=0, normalise=False).points.positions.double().sub(torch.from_numpy(points)).abs().max() < 1e-5

    (root / "transforms.json").write_text(json.dumps(meta))  # no ply_file_path: no points
    assert load_transforms(root, holdout_every=0).points is None


def test_a_missing_ply_is_named_in_a_warning_and_an_unreadable_one_refused(procedural_scene, tmp_path, caplog):
    root = write_transforms(procedural_scene.train.subset([0, 1, 2]), tmp_path / "capture")
    meta = json.loads((root / "transforms.json").read_text())
    (root / "transforms.json").write_text(json.dumps({**meta, "ply_file_path": "sparse_pc.ply"}))
    with caplog.at_level("WARNING"):
        assert load_transforms(root).points is None  # the views still load: a capture copied without its points
    assert "'ply_file_path' names" in caplog.text and "sparse_pc.ply, which is not there" in caplog.text
    (root / "sparse_pc.ply").write_text("not a point cloud")
    with pytest.raises(ValueError, match=r"'ply_file_path': could not read the sparse points in .*sparse_pc.ply"):
        load_transforms(root)


def write_points3d_bin(path, points, colours):
    """COLMAP's binary points3D.bin, each point with a track of two observations."""
    data = struct.pack("<Q", len(points))
    for index, (xyz, rgb) in enumerate(zip(points, colours)):
        data += struct.pack("<Q3d3Bd", index + 1, *xyz, *rgb, 0.5) + struct.pack("<Q", 2) + struct.pack("<4I", 1, index, 2, index)
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_bytes(data)


def test_an_llff_capture_with_a_colmap_model_brings_its_points(procedural_scene, tmp_path):
    views = procedural_scene.train.subset(list(range(8)))
    root = write_llff(views, tmp_path / "capture")
    assert load_llff(root, downscale=2, holdout_every=0).points is None
    points, colours = surface_points(views)
    write_points3d_bin(root / "sparse" / "0" / "points3D.bin", points, colours)

    scene = load_llff(root, downscale=2, holdout_every=0)  # scaled by bd_factor and recentred
    assert len(scene.points) == 300 and torch.equal(scene.points.colours, torch.from_numpy(colours))
    assert_seen_at_the_same_pixels(points, scene.points.positions, views, scene.train)

    lines = ["# 3D point list", *(f"{i + 1} {x:.17g} {y:.17g} {z:.17g} {r} {g} {b} 0.5 1 {i} 2 {i}" for i, ((x, y, z), (r, g, b)) in enumerate(zip(points, colours)))]
    (root / "sparse" / "0" / "points3D.bin").unlink()
    (root / "sparse" / "0" / "points3D.txt").write_text("\n".join(lines) + "\n")
    text = read_colmap_points(root / "sparse" / "0")
    torch.testing.assert_close(text.positions, torch.from_numpy(points).float())
    assert torch.equal(text.colours, torch.from_numpy(colours))

    (root / "sparse" / "0" / "points3D.bin").write_bytes(b"\x05" + bytes(10))
    with pytest.raises(ValueError, match=r"could not read the COLMAP points in .*points3D.bin"):
        load_llff(root, downscale=2, holdout_every=0)


def test_colmap_points_written_by_pycolmap_read_back(tmp_path):
    pycolmap = pytest.importorskip("pycolmap")
    model = pycolmap.Reconstruction()
    model.add_point3D(np.array([1.0, 2.0, 3.0]), pycolmap.Track(), np.array([10, 20, 30], dtype=np.uint8))
    model.add_point3D(np.array([-1.0, 0.5, 0.25]), pycolmap.Track(), np.array([1, 2, 3], dtype=np.uint8))
    model.write_binary(str(tmp_path))
    points = read_colmap_points(tmp_path, torch.diag(torch.tensor([2.0, 2.0, 2.0, 1.0])))
    torch.testing.assert_close(points.positions, torch.tensor([[2.0, 4.0, 6.0], [-2.0, 1.0, 0.5]]))
    assert points.colours.tolist() == [[10, 20, 30], [1, 2, 3]]
