"""Features into COLMAP's database: the images are numbered in the sorted order of their names (COLMAP sorts them
byte by byte), whatever order the extraction's threads finish them in, so that the same photos are matched, mapped
and triangulated in the same order run after run. (The old numbering passed on one core: one thread finishes the
images in order.)"""

from __future__ import annotations

import contextlib

import numpy as np
import pytest
from PIL import Image

from tests.capture.test_process_data import needs_pycolmap


@needs_pycolmap
@pytest.mark.parametrize("single_camera", [True, False])
def test_the_images_are_numbered_in_their_names_order_and_share_the_camera_asked_for(tmp_path, single_camera):
    from nerf_lightning.capture.colmap import extract_features, import_pycolmap

    images = tmp_path / "images"
    images.mkdir()
    generator = np.random.default_rng(0)
    # the first photo busy with features, the others plain but for a few squares: its thread finishes it last of its
    # chunk, and it was numbered after them. One camera is for photos of one size; with one a photo, the first is
    # larger too
    sizes = [(640, 640)] + [(640, 640) if single_camera else (160, 160)] * 5
    names = [f"{index}.png" for index in (0, 1, 2, 3, 4, 10)]  # "10.png" sorts before "2.png"
    for index, (name, (width, height)) in enumerate(zip(names, sizes)):
        if index == 0:
            pixels = generator.integers(0, 256, (height, width, 3), dtype=np.uint8)
        else:
            pixels = np.full((height, width, 3), 128, dtype=np.uint8)
            for corner in generator.integers(8, min(width, height) - 40, (6, 2)):
                pixels[corner[0]:corner[0] + 24, corner[1]:corner[1] + 24] = generator.integers(0, 256, 3)
        Image.fromarray(pixels).save(images / name)
    extract_features(tmp_path / "database.db", images, names, "PINHOLE", single_camera, 640, 8192, False)
    with contextlib.closing(import_pycolmap().Database.open(tmp_path / "database.db")) as database:
        numbered = {image.name: image.image_id for image in database.read_all_images()}
        cameras = database.read_all_cameras()
        assert all(database.num_keypoints_for_image(image_id) > 0 for image_id in numbered.values())
    assert [numbered[name] for name in sorted(names)] == sorted(numbered.values())
    assert len(cameras) == (1 if single_camera else len(names))
