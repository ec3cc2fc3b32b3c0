"""nerf-process-data: photos or a video to a posed capture with COLMAP in-process (pycolmap).

Bad captures stop with one line and leave no transforms.json; video frames are picked by sharpness and photos turned
by their EXIF orientation; ten fox photos are posed end to end against the published poses (the fifty of them in the
slow test; the camera alignment that compares them is tested in tests/geometry/test_alignment.py).
"""

from __future__ import annotations

import importlib.util
import json
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
from PIL import Image

from nerf_lightning.capture.images import write_capture_image
from nerf_lightning.errors import MissingExtraError
from tests.conftest import SHARED_DATA

FOX = SHARED_DATA / "nerfstudio" / "fox"
# ten neighbouring photos of fox's walk around the mount (published camera centres 0.13 to 0.6 apart, of a 7 wide walk)
FOX_NEIGHBOURS = ["0072", "0073", "0074", "0076", "0077", "0078", "0081", "0084", "0085", "0089"]

needs_pycolmap = pytest.mark.skipif(importlib.util.find_spec("pycolmap") is None, reason="pycolmap (the colmap extra) is not installed")
needs_fox = pytest.mark.skipif(not (FOX / "images").is_dir(), reason="fox is not in ../shared/data")


def process_data(*args: str, cwd: Path) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "nerf_lightning.cli.process_data", *args, "progress=false"], cwd=cwd,
                          capture_output=True, text=True, timeout=600)


def one_error_line(result: subprocess.CompletedProcess) -> str:
    """The run exited 2 with exactly one ``nerf-process-data: error:`` line and no traceback; that line."""
    assert result.returncode == 2, (result.returncode, result.stderr[-2000:])
    assert "Traceback" not in result.stderr
    lines = [line for line in result.stderr.splitlines() if line.startswith("nerf-process-data: error:")]
    assert len(lines) == 1, result.stderr[-2000:]
    return lines[0]


def assert_nothing_written(output: Path) -> None:
    assert not (output / "transforms.json").exists()
    assert not [path.name for path in output.parent.iterdir() if path.name.endswith(".partial")]


def noise_photos(folder: Path, count: int = 5, size: tuple[int, int] = (160, 120)) -> Path:
    folder.mkdir(parents=True, exist_ok=True)
    generator = np.random.default_rng(0)
    for index in range(count):
        Image.fromarray(generator.integers(0, 256, (size[1], size[0], 3), dtype=np.uint8)).save(folder / f"noise_{index}.jpg", quality=95)
    return folder


def fox_photos(folder: Path, names: list[str], factor: int = 4) -> Path:
    """Fox photos downscaled ``factor`` times (area averaging) into ``folder``."""
    folder.mkdir(parents=True, exist_ok=True)
    for name in names:
        with Image.open(FOX / "images" / f"{name}.jpg") as image:
            image.reduce(factor).save(folder / f"{name}.jpg", quality=95)
    return folder


# --- bad captures: one line, exit 2, nothing written


def test_a_missing_colmap_extra_names_the_install_line(tmp_path, monkeypatch):
    from nerf_lightning.capture import process_capture

    monkeypatch.setitem(sys.modules, "pycolmap", None)  # import pycolmap now raises ImportError
    with pytest.raises(MissingExtraError, match=r'pip install -c constraints-cpu.txt -e "\.\[colmap\]"'):
        process_capture(noise_photos(tmp_path / "photos"), tmp_path / "out")
    assert_nothing_written(tmp_path / "out")


@needs_pycolmap
def test_an_empty_folder_and_a_missing_input_are_named(tmp_path):
    from nerf_lightning.capture import process_capture

    (tmp_path / "empty").mkdir()
    (tmp_path / "empty" / "notes.txt").write_text("no photos here")
    with pytest.raises(ValueError, match=r"no images in .*empty"):
        process_capture(tmp_path / "empty", tmp_path / "out")
    with pytest.raises(FileNotFoundError, match="nowhere"):
        process_capture(tmp_path / "nowhere", tmp_path / "out")
    (tmp_path / "notes.txt").write_text("not a video")
    with pytest.raises(ValueError, match="not a video"):
        process_capture(tmp_path / "notes.txt", tmp_path / "out")
    assert not (tmp_path / "out").exists()


@needs_pycolmap
def test_unreadable_images_are_named_and_nothing_is_left_behind(tmp_path):
    from nerf_lightning.capture import process_capture

    photos = noise_photos(tmp_path / "photos", count=3)
    (photos / "broken.jpg").write_bytes(b"\xff\xd8\xff\xe0 this is not a JPEG")
    (photos / "IMG_0001.HEIC").write_bytes(b"\x00\x00\x00\x18ftypheic")
    with pytest.raises(ValueError, match=r"could not read 2 of the 5 images.*broken\.jpg.*IMG_0001\.HEIC.*convert them to JPEG or PNG"):
        process_capture(photos, tmp_path / "out", progress=False)
    assert_nothing_written(tmp_path / "out")


@needs_pycolmap
def test_images_of_two_sizes_need_a_camera_each(tmp_path):
    from nerf_lightning.capture import process_capture

    photos = noise_photos(tmp_path / "photos", count=3)
    Image.new("RGB", (120, 160)).save(photos / "portrait.jpg")
    with pytest.raises(ValueError, match=r"not all one size .*portrait\.jpg 120x160.*single_camera=false"):
        process_capture(photos, tmp_path / "out", progress=False)


@needs_pycolmap
def test_photos_that_do_not_register_fail_in_one_line_with_exit_2(tmp_path):
    output = tmp_path / "out"
    output.mkdir()
    (output / "notes.txt").write_text("kept")
    line = one_error_line(process_data(f"input={noise_photos(tmp_path / 'photos')}", f"output={output}", cwd=tmp_path))
    assert "registered none of the 5 images" in line and "overlap" in line
    assert "stronger settings (features at twice the size, affine shapes, guided matching) did not help either" in line
    assert_nothing_written(output)
    assert [path.name for path in output.iterdir()] == ["notes.txt"]


def test_too_few_registered_name_the_images_left_out_and_what_to_change():
    from nerf_lightning.capture.refusals import check_registered

    names = [f"IMG_{index}.jpg" for index in range(10)]
    with pytest.raises(ValueError, match=r"registered only 2 of the 10 .*IMG_0\.jpg, IMG_1\.jpg"):
        check_registered(2, names[:8], 10, Path("photos"), "exhaustive", 0.5)
    with pytest.raises(ValueError, match=r"registered 4 of the 10 .*\(40%, under min_registered=0\.5\).*IMG_9\.jpg.*"
                                         r"matcher=exhaustive.*min_registered=0 to keep the 4"):
        check_registered(4, names[4:], 10, Path("video.mp4"), "sequential", 0.5)
    check_registered(4, names[4:], 10, Path("photos"), "exhaustive", 0.4)


# --- photos and video frames made ready


def test_exif_orientation_is_applied_to_images_and_their_smaller_copies(tmp_path):
    stored = np.zeros((40, 80, 3), dtype=np.uint8)  # 80 wide, 40 high as stored
    stored[:8, :8] = (255, 0, 0)  # a red corner at the stored top left
    exif = Image.Exif()
    exif[0x0112] = 6  # the camera was turned: show the pixels turned 90 degrees clockwise
    Image.fromarray(stored).save(tmp_path / "portrait.jpg", quality=95, exif=exif)
    Image.fromarray(stored).save(tmp_path / "landscape.png")

    name, size = write_capture_image(tmp_path / "portrait.jpg", tmp_path / "out", [2, 4])
    assert (name, size) == ("portrait.jpg", (40, 80))
    with Image.open(tmp_path / "out" / "images" / "portrait.jpg") as written:
        assert written.size == (40, 80) and written.getexif().get(0x0112, 1) == 1
        pixels = np.asarray(written)
    assert pixels[:6, -6:, 0].mean() > 200 and pixels[:6, -6:, 1:].mean() < 60  # turned clockwise: the corner is now top right
    for factor in (2, 4):
        with Image.open(tmp_path / "out" / f"images_{factor}" / "portrait.jpg") as smaller:
            assert smaller.size == (40 // factor, 80 // factor)
    # an upright PNG is copied byte for byte
    assert write_capture_image(tmp_path / "landscape.png", tmp_path / "out", [2]) == ("landscape.png", (80, 40))
    assert (tmp_path / "out" / "images" / "landscape.png").read_bytes() == (tmp_path / "landscape.png").read_bytes()


def test_the_sharpest_frame_of_each_stretch_of_a_video_is_written(tmp_path):
    pytest.importorskip("imageio_ffmpeg", reason="imageio-ffmpeg (the video extra) is not installed")
    import imageio.v3 as iio

    from nerf_lightning.capture.intake import write_video_frames
    from nerf_lightning.capture.video import laplacian_variance

    generator = np.random.default_rng(0)
    texture = generator.integers(0, 256, (64, 96, 3)).astype(np.float32)
    blurred = texture.copy()
    for _ in range(6):  # a strong box blur: the out-of-focus frames
        blurred = (blurred + np.roll(blurred, 1, 0) + np.roll(blurred, -1, 0) + np.roll(blurred, 1, 1) + np.roll(blurred, -1, 1)) / 5
    sharp_frames = {3, 14, 22}  # one in each third of 30 frames
    frames = np.stack([(texture if index in sharp_frames else blurred).astype(np.uint8) for index in range(30)])
    iio.imwrite(tmp_path / "clip.mp4", frames, extension=".mp4", fps=10, codec="libx264", macro_block_size=1)
    assert laplacian_variance(frames[3]) > 5 * laplacian_variance(frames[0])

    sizes, picked = write_video_frames(tmp_path / "clip.mp4", tmp_path / "out", 3, [2], progress=False)
    assert [entry["frame"] for entry in picked] == sorted(sharp_frames)
    assert list(sizes) == ["frame_00001.jpg", "frame_00002.jpg", "frame_00003.jpg"] and set(sizes.values()) == {(96, 64)}
    assert sorted(path.name for path in (tmp_path / "out" / "images_2").iterdir()) == list(sizes)


def test_video_frames_are_spread_over_the_clip():
    from nerf_lightning.capture.video import stretches

    assert stretches(10, 3).tolist() == [0, 0, 0, 0, 1, 1, 1, 2, 2, 2]
    assert stretches(4, 10).tolist() == [0, 1, 2, 3]  # fewer frames than asked: every frame


# --- fox, posed end to end


@needs_pycolmap
@needs_fox
@pytest.mark.parametrize("mapper", ["auto", "incremental"])
def test_ten_fox_photos_are_posed_as_published(tmp_path, mapper):
    from nerf_lightning.capture import compare_with_reference
    from nerf_lightning.data.formats import load_transforms

    photos = fox_photos(tmp_path / "photos", FOX_NEIGHBOURS)
    output = tmp_path / "fox"
    started = time.perf_counter()
    result = process_data(f"input={photos}", f"output={output}", f"mapper={mapper}", cwd=tmp_path)
    seconds = time.perf_counter() - started
    assert result.returncode == 0, result.stderr[-3000:]
    assert "registered 10 of 10 images" in result.stdout and f"data.root={output}" in result.stdout
    assert seconds < 60

    report = json.loads((output / "report.json").read_text())
    assert report["registered"] == 10 and report["unregistered"] == [] and report["matcher"] == "exhaustive"
    assert set(report["mappers"]) == ({"global", "incremental"} if mapper == "auto" else {mapper}) and report["mapper"] in report["mappers"]
    assert report["verified_matches_explained"] > 0.9
    # a right model: every photo sees a hundred points or more, none is one picture twice, nothing is said
    checks = report["pose_checks"]
    assert checks["thinly_posed"] == [] and checks["repeated"] == [] and checks["refuse"] == checks["warn"] == []
    assert (checks["mappers"] is not None) == (mapper == "auto") and checks["view_graph"]["median_neighbours"] >= 2
    assert report["mean_reprojection_error_px"] < 1.5 and report["mean_track_length"] > 2.0
    meta = json.loads((output / "transforms.json").read_text())
    assert (meta["w"], meta["h"]) == (270, 480) and meta["camera_model"] == "OPENCV"
    assert meta["fl_x"] == pytest.approx(1375.5 / 4, rel=0.05)  # the published focal length, at a quarter of the size
    assert [frame["file_path"] for frame in meta["frames"]] == [f"images/{name}.jpg" for name in FOX_NEIGHBOURS]
    for factor in (2, 4, 8):
        with Image.open(output / f"images_{factor}" / "0072.jpg") as smaller:
            assert smaller.size == (270 // factor, 480 // factor)
    import trimesh

    assert len(trimesh.load(output / "sparse_pc.ply").vertices) == report["points"] > 500
    assert (output / "colmap" / "sparse" / "0" / "images.bin").is_file()

    errors = compare_with_reference(output, FOX / "transforms.json")
    assert errors["compared"] == 10
    assert errors["median_position_error_percent_of_spread"] < 2.0 and errors["median_rotation_error_deg"] < 1.0

    scene = load_transforms(output, downscale=2)  # the project's own loader reads it, lens undone
    assert len(scene.splits["train"]) + len(scene.splits["val"]) == 10 and scene.splits["train"].width == 135


@pytest.mark.slow
@needs_pycolmap
@needs_fox
def test_all_fifty_fox_photos_are_posed_within_one_percent_and_one_degree(tmp_path):
    from nerf_lightning.capture import compare_with_reference, process_capture

    report = process_capture(FOX / "images", tmp_path / "fox", progress=False)
    assert report["images_given"] == 50 and report["registered"] >= 48
    errors = compare_with_reference(tmp_path / "fox", FOX / "transforms.json")
    assert errors["compared"] >= 48
    assert errors["median_position_error_percent_of_spread"] < 1.0 and errors["median_rotation_error_deg"] < 1.0
