"""A photo's focal length in pixels from its EXIF, read for the photo as it is: a downscaled or square-cropped copy
that kept its camera's EXIF gets its own focal length, not its full frame's (COLMAP's reading, several times too long,
on which its incremental mapper fails: moldGoldCape's 912 px copies)."""

from __future__ import annotations

import pytest
from PIL import Image

from nerf_lightning.capture.images import (
    EXIF_IFD,
    FOCAL_LENGTH,
    FOCAL_LENGTH_35MM,
    FOCAL_PLANE_UNIT,
    FOCAL_PLANE_X_RESOLUTION,
    PIXEL_X,
    PIXEL_Y,
    exif_focal_length,
)
from tests.capture.test_process_data import needs_pycolmap

# a 5472x3648 sensor, 18 mm lens, 10 584 pixels an inch on the focal plane: 7500 px at full frame
FULL_FRAME = {FOCAL_LENGTH: 18.0, FOCAL_PLANE_X_RESOLUTION: 10583.333333, FOCAL_PLANE_UNIT: 2, PIXEL_X: 5472, PIXEL_Y: 3648}


def photo(path, size, tags):
    image = Image.new("RGB", size, (90, 120, 150))
    exif = image.getexif()
    exif.get_ifd(EXIF_IFD).update(tags)
    image.save(path, exif=exif)
    return path


@pytest.mark.parametrize(("size", "expected"), [
    ((5472, 3648), 7500.0),  # as the camera wrote it
    ((1368, 912), 1875.0),  # downscaled 4 times
    ((912, 912), 1875.0),  # a square crop of the frame's short side, then downscaled 4 times (moldGoldCape)
    ((912, 1368), 1875.0),  # downscaled, turned upright
])
def test_the_focal_length_follows_the_photos_own_pixels(tmp_path, size, expected):
    assert exif_focal_length(photo(tmp_path / "a.jpg", size, FULL_FRAME)) == pytest.approx(expected, rel=1e-6)


def test_the_35mm_equivalent_is_read_where_the_focal_plane_is_not_and_no_exif_gives_none(tmp_path):
    # 36 mm across the long side: 24 mm equivalent is 2/3 of the long side
    tags = {FOCAL_LENGTH_35MM: 24, PIXEL_X: 4000, PIXEL_Y: 3000}
    assert exif_focal_length(photo(tmp_path / "a.jpg", (2000, 1500), tags)) == pytest.approx(2000 * 2 / 3)
    assert exif_focal_length(photo(tmp_path / "b.jpg", (200, 150), {})) is None
    assert exif_focal_length(photo(tmp_path / "c.jpg", (200, 150), {FOCAL_LENGTH: 0.0, FOCAL_PLANE_X_RESOLUTION: 100.0})) is None


@needs_pycolmap
def test_the_cameras_focal_length_is_set_from_the_photos_own_pixels_before_matching(tmp_path):
    from nerf_lightning.capture.colmap import extract_features, import_pycolmap

    images = tmp_path / "images"
    images.mkdir()
    for index in range(3):
        photo(images / f"{index}.jpg", (456, 304), FULL_FRAME)  # downscaled 12 times: 625 px
    changed = extract_features(tmp_path / "database.db", images, ["0.jpg", "1.jpg", "2.jpg"], "OPENCV", True, 456, 512, False)
    pycolmap = import_pycolmap()
    database = pycolmap.Database.open(tmp_path / "database.db")
    cameras = database.read_all_cameras()
    database.close()
    assert len(cameras) == 1 and cameras[0].mean_focal_length() == pytest.approx(625.0, rel=1e-6)
    assert cameras[0].has_prior_focal_length
    # COLMAP's own reading of these tags is not 625 (on moldGoldCape's photos it is the full frame's; here its
    # default guess, 1.2 x the long side): the change is reported
    assert len(changed) == 1 and changed[0]["image"] == "0.jpg" and changed[0]["set_px"] == 625.0
    assert abs(changed[0]["colmap_px"] - 625.0) > 0.05 * 625.0
