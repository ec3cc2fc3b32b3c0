"""Recovered cameras against a capture's published ones: a transforms.json against a transforms.json, or against an
LLFF poses_bounds.npy whose rows are the capture's photos in name order (moldGoldCape's photographer's poses)."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest
import torch

from nerf_lightning.capture import compare_with_reference
from nerf_lightning.data.formats.llff import write_poses_bounds
from nerf_lightning.geometry.cameras import opengl_to_opencv


def orbit(count: int) -> torch.Tensor:
    """(count, 4, 4) OpenGL cameras on a circle of radius 3 looking at the origin."""
    cameras = []
    for index in range(count):
        angle = 2 * math.pi * index / count
        position = torch.tensor([3 * math.cos(angle), 3 * math.sin(angle), 0.5], dtype=torch.float64)
        back = position / position.norm()
        right = torch.linalg.cross(torch.tensor([0.0, 0.0, 1.0], dtype=torch.float64), back)
        right = right / right.norm()
        c2w = torch.eye(4, dtype=torch.float64)
        c2w[:3, :3] = torch.stack([right, torch.linalg.cross(back, right), back], dim=1)
        c2w[:3, 3] = position
        cameras.append(c2w)
    return torch.stack(cameras)


def write_transforms(folder, names, c2w):
    folder.mkdir(parents=True, exist_ok=True)
    frames = [{"file_path": f"images/{name}", "transform_matrix": matrix.tolist()} for name, matrix in zip(names, c2w)]
    (folder / "transforms.json").write_text(json.dumps({"frames": frames}))


def write_llff(folder, names, c2w):
    (folder / "images_4").mkdir(parents=True)
    for name in names:
        (folder / "images_4" / name).write_bytes(b"")  # named, not read
    write_poses_bounds(folder / "poses_bounds.npy", opengl_to_opencv(c2w), 100, 100, 80.0, np.ones((len(c2w), 2)))


def test_an_llff_reference_names_its_rows_by_the_photos_in_name_order_and_matches_by_stem(tmp_path):
    c2w = orbit(8)
    names = [f"IMG_{10 + index}.JPG" for index in range(8)]
    write_llff(tmp_path / "published", names, c2w)
    # recovered: the same cameras in another similarity frame, written as PNG copies of the photos, in another order
    similarity = torch.eye(4, dtype=torch.float64)
    similarity[:3, :3] = 2.0 * torch.tensor([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]], dtype=torch.float64)
    similarity[:3, 3] = torch.tensor([1.0, 2.0, 3.0], dtype=torch.float64)
    moved = similarity @ c2w
    moved[:, :3, :3] /= 2.0
    order = [3, 1, 0, 7, 5, 2, 6, 4]
    write_transforms(tmp_path / "ours", [names[i].replace(".JPG", ".png") for i in order], moved[order])
    errors = compare_with_reference(tmp_path / "ours", tmp_path / "published")
    assert errors["compared"] == 8
    assert errors["median_position_error_percent_of_spread"] < 1e-6 and errors["max_rotation_error_deg"] < 1e-4
    # one camera off by 10 degrees about its own axis is found, and only that one
    turned = moved[order].clone()  # row 0: IMG_13
    turn = torch.tensor([[1.0, 0.0, 0.0], [0.0, math.cos(0.1745), -math.sin(0.1745)], [0.0, math.sin(0.1745), math.cos(0.1745)]],
                        dtype=torch.float64)
    turned[0, :3, :3] = turned[0, :3, :3] @ turn
    write_transforms(tmp_path / "ours", [names[i].replace(".JPG", ".png") for i in order], turned)
    errors = compare_with_reference(tmp_path / "ours", tmp_path / "published")
    assert errors["per_image"]["IMG_13"]["rotation_error_deg"] == pytest.approx(10.0, abs=0.01)
    assert errors["median_rotation_error_deg"] < 1e-4


def test_an_llff_reference_without_a_folder_of_as_many_photos_is_refused_in_one_line(tmp_path):
    c2w = orbit(4)
    write_llff(tmp_path / "published", ["a.jpg", "b.jpg", "c.jpg"] + ["d.jpg"], c2w)
    (tmp_path / "published" / "images_4" / "d.jpg").unlink()
    write_transforms(tmp_path / "ours", ["a.jpg", "b.jpg", "c.jpg", "d.jpg"], c2w)
    with pytest.raises(ValueError, match=r"poses_bounds.npy: no images\*/ folder beside it holds its 4 images"):
        compare_with_reference(tmp_path / "ours", tmp_path / "published")
