"""Images kept as uint8, in memory or memory-mapped from a cache folder: same pixels, mapped not copied, reused, safe."""

import json
import os
import sys
from pathlib import Path

import pytest
import torch

from nerf_lightning.data.formats import blender, load_blender, load_transforms
from nerf_lightning.data.image_stack import as_float_rgb, stack_images
from nerf_lightning.data.images import load_image
from nerf_lightning.io import write_png
from tests.data.test_formats import copy_procedural
from tests.data.test_transforms import write_transforms


def mapped_files() -> set[str]:
    """The files this process has memory-mapped (Linux)."""
    lines = Path("/proc/self/maps").read_text().splitlines()
    return {line.split(maxsplit=5)[5] for line in lines if len(line.split(maxsplit=5)) == 6}


def storage(images: torch.Tensor) -> int:
    return images.untyped_storage().data_ptr()


def test_the_cache_holds_the_same_pixels_mapped_from_one_file_a_split(procedural_scene, scene_cache, tmp_path):
    root = copy_procedural(scene_cache, tmp_path)
    in_memory = load_blender(root, max_views=6)
    mapped = load_blender(root, max_views=6, image_cache=tmp_path / "cache")
    files = sorted((tmp_path / "cache").glob("*.u8"))
    assert [f.name.split("-")[1] for f in files] == ["test", "train", "val"]  # <scene>-<split>-<hash>.u8
    for split in ("train", "val", "test"):
        assert mapped.splits[split].images.dtype == torch.uint8
        assert torch.equal(mapped.splits[split].images, in_memory.splits[split].images)
    meta = json.loads(files[1].with_suffix(".json").read_text())
    assert meta["shape"] == [6, 100, 100, 3] and files[1].stat().st_size == 6 * 100 * 100 * 3
    if sys.platform.startswith("linux"):
        assert {str(f) for f in files} <= mapped_files()  # mapped, not read into memory


def test_the_cache_is_reused_until_an_image_or_a_setting_changes(procedural_scene, scene_cache, tmp_path, monkeypatch):
    root = copy_procedural(scene_cache, tmp_path)
    cache = tmp_path / "cache"
    first = load_blender(root, max_views=4, image_cache=cache)
    decoded = []
    original = blender.load_image
    monkeypatch.setattr(blender, "load_image", lambda path, **kw: decoded.append(Path(path).name) or original(path, **kw))
    again = load_blender(root, max_views=4, image_cache=cache)
    assert decoded == [] and torch.equal(again.train.images, first.train.images)  # nothing decoded again
    assert len(list(cache.glob("*.u8"))) == 3

    image = root / "train" / "r_0.png"
    write_png(image, torch.zeros(100, 100, 3))  # the file changes: its split is decoded again, into a file of its own
    os.utime(image, ns=(image.stat().st_atime_ns, image.stat().st_mtime_ns + 10**9))
    changed = load_blender(root, max_views=4, image_cache=cache)
    assert len(decoded) == 4 and "r_0.png" in decoded  # train again; val and test reused
    assert (changed.train.images[0] == 0).all() and len(list(cache.glob("*.u8"))) == 4
    decoded.clear()
    half = load_blender(root, max_views=4, downscale=2, image_cache=cache)  # another setting: other files
    assert len(decoded) == 12 and half.train.images.shape[1:] == (50, 50, 3) and len(list(cache.glob("*.u8"))) == 7


def test_a_damaged_cache_file_is_written_again(procedural_scene, scene_cache, tmp_path):
    root = copy_procedural(scene_cache, tmp_path)
    cache = tmp_path / "cache"
    load_blender(root, max_views=3, image_cache=cache)  # not kept: nothing maps the files when they are cut short below
    for data in cache.glob("*.u8"):
        data.write_bytes(data.read_bytes()[:1000])  # as a full disk or a copy cut short would leave it
    again = load_blender(root, max_views=3, image_cache=cache)
    assert torch.equal(again.train.images, load_blender(root, max_views=3).train.images)
    assert all(data.stat().st_size == 3 * 100 * 100 * 3 for data in cache.glob("*.u8"))


def test_a_failed_decode_leaves_no_cache_file(tmp_path):
    paths = [tmp_path / f"{i}.png" for i in range(3)]
    for path in paths[:2]:
        write_png(path, torch.full((4, 4, 3), 0.5))
    paths[2].write_bytes(b"no PNG")

    with pytest.raises(ValueError, match=r"could not read image .*2.png"):
        stack_images(paths, load_image, cache=tmp_path / "cache")
    assert list((tmp_path / "cache").iterdir()) == []


def test_images_of_another_size_are_named_in_memory_and_on_disk(tmp_path):
    paths = [tmp_path / "a.png", tmp_path / "b.png"]
    write_png(paths[0], torch.zeros(4, 6, 3))
    write_png(paths[1], torch.zeros(5, 6, 3))
    for cache in (None, tmp_path / "cache"):
        with pytest.raises(ValueError, match=r"b.png is 6x5 but a.png is 6x4: all images of a split must have one size"):
            stack_images(paths, load_image, cache=cache)


def test_a_cache_folder_that_cannot_be_written_is_named(tmp_path):
    (tmp_path / "a_file").write_text("")
    write_png(tmp_path / "a.png", torch.zeros(4, 4, 3))
    with pytest.raises(PermissionError, match=r"cannot write to the folder .*a_file/cache .*data.scene.image_cache="):
        stack_images([tmp_path / "a.png"], load_image, cache=tmp_path / "a_file" / "cache")


def test_split_views_are_slices_of_one_mapped_stack(procedural_scene, tmp_path):
    views = procedural_scene.train.subset(list(range(10)))
    root = write_transforms(views, tmp_path / "capture")
    scene = load_transforms(root, holdout_every=4, normalise=False, image_cache=tmp_path / "cache")
    train, val = scene.train, scene.splits["val"]
    assert [len(train), len(val)] == [7, 3] and len(list((tmp_path / "cache").glob("*.u8"))) == 1
    assert storage(train.images) == storage(val.images) == storage(scene.splits["test"].images)  # views, not copies
    assert torch.equal(train.images, views.images[[1, 2, 3, 5, 6, 7, 9]]) and torch.equal(val.images, views.images[[0, 4, 8]])
    assert train.names[0] == "0001.png" and val.names == ["0000.png", "0004.png", "0008.png"]
    every_other = train.subset([0, 2])  # not a run of views: copied
    assert storage(every_other.images) != storage(train.images) and torch.equal(every_other.images, train.images[[0, 2]])


def test_as_float_rgb():
    assert torch.equal(as_float_rgb(torch.tensor([0, 51, 255], dtype=torch.uint8)), torch.tensor([0.0, 0.2, 1.0]))
    floats = torch.rand(2, 3)
    assert as_float_rgb(floats) is floats
