"""nerf-process-data camera_model=OPENCV_FISHEYE on the procedural turntable photographed through a fisheye lens
(90 degrees across, Kannala-Brandt k1..k4): posed within 2% and 2 degrees, the lens written as nerfstudio writes it
(k1..k4, no p1/p2), the masks' agreement carved in the pinhole views the loader makes, and the capture loaded back."""

from __future__ import annotations

import json

import pytest

from nerf_lightning.capture import compare_with_reference
from nerf_lightning.data.formats import load_transforms, make_turntable_capture
from tests.capture.test_process_data import needs_pycolmap, process_data

FISHEYE = (0.05, -0.02, 0.004, -0.0005)  # k1..k4, a GoPro-like lens
SIZE, FOV, DISTANCE = 320, 90.0, 2.0  # wide enough that a pinhole would misplace the rim, near enough that the object fills it


@pytest.fixture(scope="module")
def fisheye_turntable(tmp_path_factory):
    return make_turntable_capture(tmp_path_factory.mktemp("fisheye") / "capture", size=SIZE, fov_degrees=FOV, distance=DISTANCE,
                                  fisheye=FISHEYE)


def test_the_fisheye_turntable_is_written_as_opencv_fisheye_and_loads_as_pinhole_views(fisheye_turntable):
    meta = json.loads((fisheye_turntable / "transforms.json").read_text())
    assert meta["camera_model"] == "OPENCV_FISHEYE" and [meta[key] for key in ("k1", "k2", "k3", "k4")] == list(FISHEYE)
    scene = load_transforms(fisheye_turntable, holdout_every=8)
    # the pinhole views keep the photos' size; a fisheye squeezes, so the views' focal is the photo's (lenses.py)
    assert scene.train.images.shape[1:3] == (SIZE, SIZE)


@needs_pycolmap
def test_a_fisheye_capture_is_posed_with_its_lens(fisheye_turntable, tmp_path):
    output = tmp_path / "posed"
    result = process_data(f"input={fisheye_turntable / 'images'}", f"masks={fisheye_turntable / 'masks'}", f"output={output}",
                          "camera_model=OPENCV_FISHEYE", cwd=tmp_path)
    assert result.returncode == 0, result.stderr[-3000:]
    report = json.loads((output / "report.json").read_text())
    assert report["registered"] >= 0.9 * report["images_given"], report["unregistered"]
    errors = compare_with_reference(output, fisheye_turntable)
    assert errors["max_position_error_percent_of_spread"] < 2.0 and errors["max_rotation_error_deg"] < 2.0, errors
    meta = json.loads((output / "transforms.json").read_text())
    truth = json.loads((fisheye_turntable / "transforms.json").read_text())
    assert meta["camera_model"] == "OPENCV_FISHEYE" and {"k1", "k2", "k3", "k4"} <= set(meta) and not {"p1", "p2"} & set(meta)
    assert meta["fl_x"] == pytest.approx(truth["fl_x"], rel=0.03) and meta["cx"] == pytest.approx(truth["cx"], abs=2.0)
    assert report["silhouettes"]["median_coverage"] > 0.9, report["silhouettes"]
    scene = load_transforms(output, holdout_every=8)  # the loader undistorts what COLMAP fitted
    assert scene.train.images.shape[1:3] == (SIZE, SIZE)
