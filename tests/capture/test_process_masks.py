"""nerf-process-data masks=<folder>: a mask a photo, matched by name, turned upright by EXIF as the photos are, read
as white (or black) = object; written as masks/ and masks_<k>/ lined up with images/ and images_<k>/, named by each
transforms.json frame's ``mask_path``, and handed to COLMAP so that only the object's features are extracted.

Bad masks stop with one line naming the file and leave nothing behind. Registration of a masked capture end to end
is tested on the turntable scene (nerf_lightning.data.formats.turntable), not here.
"""

from __future__ import annotations

import contextlib
import json
from pathlib import Path

import numpy as np
import pytest
from PIL import Image

from nerf_lightning.capture.images import find_masks, mask_name, read_mask
from tests.capture.test_process_data import assert_nothing_written, needs_pycolmap, one_error_line, process_data

SIZE = (161, 121)  # (width, height): odd, so that images_<k> and masks_<k> crop a remainder


def object_mask(size: tuple[int, int], index: int) -> np.ndarray:
    """(H, W) bool: an ellipse off centre, moved with ``index``, and a bar across its top, edges on no block grid."""
    width, height = size
    y, x = np.mgrid[:height, :width]
    centre_x, centre_y = 0.45 * width + 7 * index, 0.55 * height - 3 * index
    ellipse = ((x - centre_x) / (0.27 * width)) ** 2 + ((y - centre_y) / (0.31 * height)) ** 2 <= 1.0
    bar = (abs(y - 0.2 * height) < 3.3) & (x > 0.13 * width) & (x < 0.71 * width)
    return ellipse | bar


def object_photos(folder: Path, count: int = 3, size: tuple[int, int] = SIZE) -> Path:
    """PNG photos whose red channel is 255 on ``object_mask`` and 0 elsewhere (green: noise, for texture)."""
    folder.mkdir(parents=True, exist_ok=True)
    generator = np.random.default_rng(0)
    for index in range(count):
        pixels = np.zeros((size[1], size[0], 3), np.uint8)
        pixels[..., 0] = object_mask(size, index) * 255
        pixels[..., 1] = generator.integers(0, 256, (size[1], size[0]), dtype=np.uint8)
        Image.fromarray(pixels).save(folder / f"photo_{index}.png")
    return folder


def textured_photos(folder: Path, count: int = 3, size: tuple[int, int] = (320, 240)) -> Path:
    """JPEG photos of smooth noise (blobs at every scale: SIFT finds keypoints all over them)."""
    folder.mkdir(parents=True, exist_ok=True)
    generator = np.random.default_rng(1)
    for index in range(count):
        coarse = generator.integers(0, 256, (size[1] // 4, size[0] // 4, 3), dtype=np.uint8)
        Image.fromarray(coarse).resize(size, Image.BICUBIC).save(folder / f"photo_{index}.jpg", quality=95)
    return folder


def save_masks(folder: Path, photos: Path, kind: str = "white", size: tuple[int, int] | None = None) -> Path:
    """A mask of ``object_mask`` for each photo in ``photos``, stored as ``kind`` says: white or black (inverted)
    PNG, a JPEG (white, compression noise around its edges), 0s and 1s, or named nerfstudio's way (photo.jpg.png)."""
    folder.mkdir(parents=True, exist_ok=True)
    for index, photo in enumerate(sorted(photos.iterdir())):
        with Image.open(photo) as opened:
            mask = object_mask(size or opened.size, index)
        if kind == "black":
            Image.fromarray((~mask).astype(np.uint8) * 255).save(folder / f"{photo.stem}.png")
        elif kind == "jpeg":
            Image.fromarray(mask.astype(np.uint8) * 255).save(folder / f"{photo.stem}.jpg", quality=70)
        elif kind == "zero_one":
            Image.fromarray(mask.astype(np.uint8)).save(folder / f"{photo.stem}.png")
        elif kind == "nerfstudio":
            Image.fromarray(mask.astype(np.uint8) * 255).save(folder / f"{photo.name}.png")
        else:
            Image.fromarray(mask.astype(np.uint8) * 255).save(folder / f"{photo.stem}.png")
    return folder


def stage(photos: Path, masks: Path, staging: Path, mask_object: str = "white", downscales=(2, 4)) -> tuple[dict, dict]:
    """photos and masks written into ``staging`` as process_capture writes them: the images' sizes and the masks'
    object fractions, by image name."""
    from nerf_lightning.capture.images import find_images
    from nerf_lightning.capture.intake import write_masks, write_photos

    paths = find_images(photos)
    sizes = write_photos(paths, staging, downscales, progress=False)
    return sizes, write_masks(find_masks(masks, paths), sizes, staging, downscales, mask_object, progress=False)


def grey(path: Path) -> np.ndarray:
    with Image.open(path) as image:
        assert image.mode == "L"
        return np.asarray(image)


def dilated(mask: np.ndarray, pixels: int) -> np.ndarray:
    """(H, W) bool grown by ``pixels`` in every direction (a square neighbourhood)."""
    padded = np.pad(mask, pixels)
    height, width = mask.shape
    grown = np.zeros_like(mask)
    for dy in range(2 * pixels + 1):
        for dx in range(2 * pixels + 1):
            grown |= padded[dy : dy + height, dx : dx + width]
    return grown


# --- bad masks: one line naming the file, nothing written


def break_masks(case: str, photos: Path, masks: Path) -> None:
    if case == "without":
        (masks / "photo_1.png").unlink()
        (masks / "photo_2.png").unlink()
    elif case == "size":
        Image.new("L", (100, 80), 255).save(masks / "photo_2.png")
    elif case == "unreadable":
        (masks / "photo_1.png").write_bytes(b"\x89PNG\r\n\x1a\n not a PNG after all")
    elif case == "background":
        Image.new("L", SIZE, 0).save(masks / "photo_0.png")
    elif case == "object":
        Image.new("L", SIZE, 255).save(masks / "photo_1.png")
    elif case == "two":
        Image.new("L", SIZE, 255).save(masks / "photo_0.png.png")


ERRORS = {
    "missing": (FileNotFoundError, r"masks folder not found: .*nowhere"),
    "without": (ValueError, r"2 of the 3 photos have no mask in .*masks: photo_1\.png, photo_2\.png; a mask is named as its photo"),
    "size": (ValueError, r"mask photo_2\.png is 100x80 but its photo photo_2\.png is 161x121"),
    "unreadable": (ValueError, r"could not read 1 of the 3 masks in .*masks: photo_1\.png \("),
    "background": (ValueError, r"mask photo_0\.png \(of photo_0\.png\) is all background, nothing to match.*mask_object=black"),
    "object": (ValueError, r"mask photo_1\.png \(of photo_1\.png\) is all object, it leaves nothing out.*mask_object=black"),
    "two": (ValueError, r"photo_0\.png has 2 masks in .*\(photo_0\.png, photo_0\.png\.png\); keep one"),
    "video": (ValueError, r"masks are not supported with a video input \(clip\.mp4\)"),
}


@needs_pycolmap
@pytest.mark.parametrize("case", list(ERRORS))
def test_bad_masks_stop_in_one_line_naming_the_file(tmp_path, case):
    from nerf_lightning.capture import process_capture

    photos = object_photos(tmp_path / "photos")
    masks = save_masks(tmp_path / "masks", photos)
    break_masks(case, photos, masks)
    source = photos
    if case == "missing":
        masks = tmp_path / "nowhere"
    if case == "video":
        source = tmp_path / "clip.mp4"
        source.write_bytes(b"not read: masks are refused first")
    error, message = ERRORS[case]
    with pytest.raises(error, match=message) as raised:
        process_capture(source, tmp_path / "out", masks=masks, progress=False)
    assert "\n" not in str(raised.value)
    assert not (tmp_path / "out").exists()
    assert_nothing_written(tmp_path / "out")


@needs_pycolmap
def test_a_bad_mask_from_the_command_line_is_one_error_line_and_exit_2(tmp_path):
    photos = object_photos(tmp_path / "photos")
    masks = save_masks(tmp_path / "masks", photos)
    Image.new("L", (121, 161), 255).save(masks / "photo_1.png")  # turned: drawn on another copy of the photo
    output = tmp_path / "out"
    output.mkdir()
    (output / "notes.txt").write_text("kept")
    line = one_error_line(process_data(f"input={photos}", f"output={output}", f"masks={masks}", cwd=tmp_path))
    assert "mask photo_1.png is 121x161 but its photo photo_1.png is 161x121" in line and "EXIF" in line
    assert_nothing_written(output)
    assert [path.name for path in output.iterdir()] == ["notes.txt"]


def test_mask_keys_are_checked_before_anything_loads(tmp_path):
    line = one_error_line(process_data("input=photos", "output=out", "mask_object=grey", cwd=tmp_path))
    assert line.endswith("mask_object must be white or black, got 'grey'")
    line = one_error_line(process_data("input=photos", "output=out", "masks=[a,b]", cwd=tmp_path))
    assert "masks must be a folder with a mask for each photo or null" in line


# --- masks written


@pytest.mark.parametrize("kind", ["white", "black", "jpeg", "zero_one", "nerfstudio"])
def test_masks_are_written_full_size_and_lined_up_with_the_smaller_images(tmp_path, kind):
    photos = object_photos(tmp_path / "photos")
    masks = save_masks(tmp_path / "masks", photos, kind)
    if kind == "jpeg":  # the compression left noise around the edges, which the half-white threshold takes out
        values = grey(masks / "photo_0.jpg")
        assert ((values > 0) & (values < 255)).sum() > 100
    staging = tmp_path / "staging"
    sizes, fractions = stage(photos, masks, staging, mask_object="black" if kind == "black" else "white")
    assert list(fractions) == list(sizes) == ["photo_0.png", "photo_1.png", "photo_2.png"]
    for index, name in enumerate(sizes):
        expected = object_mask(SIZE, index)
        written = grey(staging / "masks" / name)
        assert written.shape == expected.shape and set(np.unique(written)) == {0, 255}
        np.testing.assert_array_equal(written == 255, expected)
        assert fractions[name] == pytest.approx(expected.mean())
        # COLMAP's copy, named <image name>.png, the same pixels
        assert (staging / "colmap" / "masks" / f"{name}.png").read_bytes() == (staging / "masks" / name).read_bytes()
        for factor in (2, 4):
            smaller = grey(staging / f"masks_{factor}" / name)
            with Image.open(staging / f"images_{factor}" / name) as image:
                assert image.size == (smaller.shape[1], smaller.shape[0]) == (SIZE[0] // factor, SIZE[1] // factor)
                red = np.asarray(image)[..., 0].astype(int)  # the object's share of each pixel, times 255
            # pixel for pixel: the object where it covers at least half of images_<k>'s pixel (a tie may round either way)
            clear = abs(red - 127.5) > 1
            np.testing.assert_array_equal((smaller == 255)[clear], (red >= 128)[clear])
            assert clear.mean() > 0.95


def test_masks_are_turned_upright_by_their_exif_orientation_as_the_photos_are(tmp_path):
    from nerf_lightning.capture.intake import write_masks, write_photos

    stored = np.zeros((40, 80), bool)  # 80 wide, 40 high as stored; the object at the stored top left
    stored[:10, :20] = True
    exif = Image.Exif()
    exif[0x0112] = 6  # turned 90 degrees clockwise when shown
    photos = tmp_path / "photos"
    photos.mkdir()
    for name in ("a", "b", "c"):
        Image.fromarray(np.stack([stored * 255] * 3, axis=-1).astype(np.uint8)).save(photos / f"{name}.jpg", quality=95, exif=exif)
    masks = tmp_path / "masks"
    masks.mkdir()
    Image.fromarray(stored.astype(np.uint8) * 255).save(masks / "a.jpg", quality=95, exif=exif)  # turned by its own tag
    Image.fromarray(np.rot90(stored, -1).astype(np.uint8) * 255).save(masks / "b.png")  # drawn upright
    Image.fromarray(np.rot90(stored, -1).astype(np.uint8) * 255).save(masks / "c.png")
    upright = np.rot90(stored, -1)  # 40 wide, 80 high: the object now at the top right
    np.testing.assert_array_equal(read_mask(masks / "a.jpg"), upright)

    paths = sorted(photos.iterdir())
    sizes = write_photos(paths, tmp_path / "staging", [2], progress=False)
    write_masks(find_masks(masks, paths), sizes, tmp_path / "staging", [2], "white", progress=False)
    for name in ("a", "b"):
        np.testing.assert_array_equal(grey(tmp_path / "staging" / "masks" / f"{name}.png") == 255, upright)

    Image.fromarray(stored.astype(np.uint8) * 255).save(masks / "c.png")  # drawn on the pixels as stored, no tag
    with pytest.raises(ValueError, match=r"mask c\.png is 80x40 but its photo c\.jpg is 40x80 \(upright\) \(drawn on the photo as stored"):
        write_masks(find_masks(masks, paths), sizes, tmp_path / "staging2", [2], "white", progress=False)


def test_a_sixteen_bit_and_a_palette_mask_are_read_as_the_loader_reads_them(tmp_path):
    mask = object_mask(SIZE, 0)
    Image.fromarray(mask.astype(np.uint16) * 65535).save(tmp_path / "sixteen.png")
    palette = Image.frombytes("P", SIZE, mask.astype(np.uint8).tobytes())  # indices 0 and 1
    palette.putpalette([0, 0, 0, 128, 0, 0] + [0] * 762)  # DAVIS's: index 1, dark red, is the object
    palette.save(tmp_path / "palette.png")
    np.testing.assert_array_equal(read_mask(tmp_path / "sixteen.png"), mask)
    np.testing.assert_array_equal(read_mask(tmp_path / "palette.png"), mask)
    np.testing.assert_array_equal(read_mask(tmp_path / "sixteen.png", "black"), ~mask)


def synthetic_model(names: list[str], size: tuple[int, int]):
    """A pycolmap model of registered cameras (COLMAP's synthetic dataset) whose images bear ``names``."""
    import pycolmap

    options = pycolmap.SyntheticDatasetOptions()
    options.num_rigs, options.num_frames_per_rig, options.num_points3D = 1, len(names), 50
    options.camera_width, options.camera_height = size
    options.camera_model_id = pycolmap.CameraModelId.PINHOLE
    options.camera_params = [1.2 * max(size), 1.2 * max(size), size[0] / 2, size[1] / 2]
    model = pycolmap.synthesize_dataset(options)
    for image_id, name in zip(sorted(model.reg_image_ids()), names):
        model.image(image_id).name = name
    return model


@needs_pycolmap
def test_transforms_frames_name_their_masks_and_a_later_run_replaces_them(tmp_path, monkeypatch):
    import nerf_lightning.capture.posing as posing
    from nerf_lightning.capture import format_report, process_capture

    photos = object_photos(tmp_path / "photos", count=4)
    masks = save_masks(tmp_path / "masks", photos, "black")
    names = [f"photo_{index}.png" for index in range(4)]
    handed = {}

    def reconstruct(images, names, colmap_dir, *, masks=None, **options):  # COLMAP's part stood in for: see the test below
        handed["masks"] = sorted(path.name for path in masks.iterdir()) if masks is not None else None
        mapping = {"mapper": "incremental", "mappers": {"incremental": {"registered": len(names), "verified_matches_explained": 1.0}},
                   "matches": MATCHES, "focal_priors": [], "other_model": None}
        return synthetic_model(list(names), SIZE), {"features": 0.0, "matching": 0.0, "mapping": 0.0}, mapping

    monkeypatch.setattr(posing, "reconstruct", reconstruct)
    monkeypatch.setattr(posing, "pose_checks", lambda *_: dict(NOTHING_FOUND))
    output = tmp_path / "out"
    # the stand-in model's poses are not the photos': the masks' check against them is taken off, and with it the
    # second posing it would ask for (tests/capture/test_silhouettes.py, and the escalation tests below)
    report = process_capture(photos, output, masks=masks, mask_object="black", downscales=[2, 4], min_mask_agreement=0.0,
                             escalate=False, progress=False)
    assert handed["masks"] == [f"{name}.png" for name in names]  # as COLMAP reads them: photo_0.png.png
    assert sorted(report["silhouettes"]["coverage"]) == names
    meta = json.loads((output / "transforms.json").read_text())
    assert [frame["mask_path"] for frame in meta["frames"]] == [f"masks/photo_{index}.png" for index in range(4)]
    assert all((output / frame["mask_path"]).is_file() for frame in meta["frames"])
    assert sorted(path.name for path in output.iterdir()) == ["colmap", "images", "images_2", "images_4", "masks", "masks_2",
                                                              "masks_4", "report.json", "sparse_pc.ply", "transforms.json"]
    assert not (output / "colmap" / "masks").exists()  # COLMAP's copies, by image name, are not kept
    expected_fraction = np.mean([object_mask(SIZE, index).mean() for index in range(4)])
    assert report["masks"] == {"folder": str(masks), "mask_object": "black", "count": 4,
                               "mean_object_fraction": pytest.approx(expected_fraction, abs=1e-4)}
    assert json.loads((output / "report.json").read_text())["masks"]["count"] == 4
    assert json.loads((output / "report.json").read_text())["photo_side"] == max(SIZE)
    printed = format_report(report)
    assert f"masks: 4 from {masks} (black = object), on average {100 * expected_fraction:.0f}% of a photo" in printed
    # the object alone next, on the photos themselves: 161 px a side needs no smaller copy and no patches
    assert printed.splitlines()[-2:] == [
        f"next: nerf-train experiment=splat_object_cpu data.root={output} data.scene.downscale=1",
        f"  or a NeRF of the object in its box: nerf-train experiment=nerfacto_object_cpu data.root={output} data.scene.downscale=1"]

    # a later run without masks and with fewer downscales leaves no masks or smaller copies of the first
    report = process_capture(photos, output, downscales=[2], progress=False)
    assert handed["masks"] is None and "masks" not in report
    assert sorted(path.name for path in output.iterdir()) == ["colmap", "images", "images_2", "report.json", "sparse_pc.ply",
                                                              "transforms.json"]
    assert all("mask_path" not in frame for frame in json.loads((output / "transforms.json").read_text())["frames"])
    printed = format_report(report)
    assert "\nmasks:" not in printed and printed.endswith(f"next: nerf-train experiment=fast_unbounded data.root={output}")


@needs_pycolmap
def test_masks_inside_the_output_they_would_be_replaced_by_are_refused(tmp_path):
    from nerf_lightning.capture import process_capture

    photos = object_photos(tmp_path / "photos")
    masks = save_masks(tmp_path / "out" / "masks", photos)
    with pytest.raises(ValueError, match=r"masks=.*out/masks is inside the output"):
        process_capture(photos, tmp_path / "out", masks=masks, progress=False)
    assert sorted(path.name for path in masks.iterdir()) == ["photo_0.png", "photo_1.png", "photo_2.png"]


# --- COLMAP extracts features on the object alone


@needs_pycolmap
@pytest.mark.parametrize("max_size", [128, 1600])
def test_colmap_keeps_only_the_keypoints_inside_the_masks(tmp_path, max_size):
    """COLMAP scales the keypoints of the image it read at ``max_size`` back to full-size pixels before it drops those
    on the full-size mask's zeros: every keypoint lies in its mask (grown by 2 pixels for rounding) at any
    ``max_size``; without the masks, many lie outside."""
    import pycolmap

    from nerf_lightning.capture.colmap import colmap_log, extract_features

    size = (320, 240)
    photos = textured_photos(tmp_path / "photos", size=size)
    masks = save_masks(tmp_path / "masks", photos, "jpeg")
    staging = tmp_path / "staging"
    sizes, _ = stage(photos, masks, staging)
    names = list(sizes)
    objects = {name: grey(staging / "masks" / mask_name(name)) == 255 for name in names}

    def keypoints(database: Path, masked: bool) -> dict[str, np.ndarray]:
        with colmap_log(False):
            extract_features(database, staging / "images", names, "OPENCV", True, max_size, 2048, progress=False,
                             masks=staging / "colmap" / "masks" if masked else None)
        with contextlib.closing(pycolmap.Database.open(database)) as opened:
            return {image.name: opened.read_keypoints(image.image_id)[:, :2] for image in opened.read_all_images()}

    masked, unmasked = keypoints(tmp_path / "masked.db", True), keypoints(tmp_path / "unmasked.db", False)
    assert sorted(masked) == sorted(unmasked) == names
    for name in names:
        # COLMAP's pixel (i, j) spans [i, i + 1) x [j, j + 1): a keypoint's pixel is its coordinates rounded down
        columns, rows = masked[name][:, 0].astype(int), masked[name][:, 1].astype(int)
        assert len(columns) >= 10, (name, len(columns))
        assert dilated(objects[name], 2)[rows.clip(0, size[1] - 1), columns.clip(0, size[0] - 1)].all(), name
        assert ((columns >= 0) & (columns < size[0]) & (rows >= 0) & (rows < size[1])).all()
        outside = ~objects[name][unmasked[name][:, 1].astype(int).clip(0, size[1] - 1), unmasked[name][:, 0].astype(int).clip(0, size[0] - 1)]
        assert outside.mean() > 0.3, (name, outside.mean())


# what the pose checks find in a stand-in COLMAP's model: nothing to leave out or refuse (model_checks.pose_checks)
NOTHING_FOUND = {"thinly_posed": [], "points_seen": {}, "repeated": [], "camera_spread": 1.0, "view_graph": {}, "mappers": None,
                 "refuse": [], "warn": []}
# what a stand-in COLMAP's features and matching left (colmap.database_statistics)
MATCHES = {"keypoints_mean": 812.0, "keypoints_min": 40, "pairs_matched": 15, "pairs_verified": 4, "inliers_per_verified_pair": 31.0}


def stand_in_reconstruct(calls: list, posed=None, mapper: str = "global"):
    """COLMAP's part stood in for: each call's options appended to ``calls``, a synthetic model of the photos
    ``posed(names, options)`` picks (all of them by default), registered by ``mapper``."""
    def reconstruct(images, names, colmap_dir, *, masks=None, **options):
        calls.append(options)
        colmap_dir.mkdir(parents=True, exist_ok=True)
        chosen = list(names) if posed is None else posed(names, options)
        mapping = {"mapper": mapper, "mappers": {mapper: {"registered": len(chosen), "verified_matches_explained": 1.0}},
                   "matches": MATCHES, "focal_priors": [], "other_model": None}
        return synthetic_model(chosen, SIZE), {"features": 1.0, "matching": 1.0, "mapping": 1.0}, mapping

    return reconstruct


def masks_agree(*_, **__):
    """The masks' check stood in for: the stand-in models' poses are not the photos', so their masks are taken to agree."""
    return {"median_coverage": 0.95, "views_below": [], "coverage": {}, "masks_read": "masks"}


@needs_pycolmap
@pytest.mark.parametrize("escalate", [True, False])
def test_a_capture_that_registers_too_few_is_posed_again_with_stronger_settings_and_says_so(tmp_path, monkeypatch, escalate, caplog):
    import nerf_lightning.capture.posing as posing
    from nerf_lightning.capture import format_report, process_capture

    photos = object_photos(tmp_path / "photos", count=6)
    masks = save_masks(tmp_path / "masks", photos)
    calls = []

    # 3 of 6 registered, then (stronger) 6 of 6
    monkeypatch.setattr(posing, "reconstruct", stand_in_reconstruct(calls, lambda names, options: list(names) if options.get("strong")
                                                                     else list(names)[:3], mapper="incremental"))
    monkeypatch.setattr(posing, "pose_checks", lambda *_: dict(NOTHING_FOUND))
    monkeypatch.setattr(posing, "silhouette_agreement", masks_agree)  # so that the count alone decides
    report = process_capture(photos, tmp_path / "out", masks=masks, max_size=1600, max_features=8192, min_registered=0.4, min_mask_agreement=0.0,
                             escalate=escalate, progress=False)
    if not escalate:
        assert len(calls) == 1 and report["registered"] == 3 and "escalated" not in report
        return
    # the photos are 161 px across: features at their own size or max_size, whichever is more; as many features (guided matching costs their square)
    assert calls[1]["strong"] and calls[1]["max_size"] == 1600 and calls[1]["max_features"] == 8192
    # six photos: every pair again (a photo the first pass left out has no verified pair to follow)
    assert calls[0]["matcher"] == "exhaustive" and calls[1]["matcher"] == "exhaustive" == report["escalated"]["matcher"]
    assert calls[1]["verified_in"] == calls[1]["verified_in"].parent.parent / "colmap" / "database.db"
    assert report["escalated"]["matches_before"] == MATCHES
    assert report["registered"] == 6 and report["escalated"]["registered_before"] == 3 and report["escalated"]["registered_after"] == 6
    assert len(json.loads((tmp_path / "out" / "transforms.json").read_text())["frames"]) == 6
    assert "too few registered at first (3): posed again with stronger settings" in format_report(report)
    # why the first pass registered few, in the warning: the features a photo and the matches a pair
    assert "812 features a photo on average, 40 in the fewest; 4 of 15 pairs matched verified a geometry, 31 matches a verified pair" in caplog.text


@needs_pycolmap
@pytest.mark.parametrize("check_poses", [True, False])
def test_photos_posed_on_almost_no_points_are_left_out_named_and_counted_against_the_floor(tmp_path, monkeypatch, caplog, check_poses):
    import nerf_lightning.capture.posing as posing
    from nerf_lightning.capture import format_report, process_capture

    photos = object_photos(tmp_path / "photos", count=6)
    masks = save_masks(tmp_path / "masks", photos)

    thin = ["photo_1.png", "photo_4.png"]
    monkeypatch.setattr(posing, "reconstruct", stand_in_reconstruct([]))
    monkeypatch.setattr(posing, "pose_checks", lambda *_: {**NOTHING_FOUND, "thinly_posed": thin, "warn": ["2 of the 6 posed photos ..."]})
    monkeypatch.setattr(posing, "silhouette_agreement", masks_agree)
    report = process_capture(photos, tmp_path / "out", masks=masks, min_mask_agreement=0.0, escalate=False, progress=False,
                             check_poses=check_poses)
    frames = [frame["file_path"] for frame in json.loads((tmp_path / "out" / "transforms.json").read_text())["frames"]]
    if not check_poses:  # kept, as before the checks
        assert report["registered"] == 6 and report["left_out"] == [] and len(frames) == 6
        return
    assert report["registered"] == 4 and report["left_out"] == thin and report["unregistered"] == []
    assert frames == [f"images/photo_{k}.png" for k in (0, 2, 3, 5)]
    assert "left out, posed on fewer than 6 of the model's points: photo_1.png, photo_4.png" in format_report(report)
    assert "2 of the 6 posed photos" in caplog.text
    # four of six under a floor of 0.9: refused, the two named as not posed, not as unregistered
    with pytest.raises(ValueError, match=r"COLMAP posed \(registered, less 2 seeing fewer than 6 of its points\) 4 of the 6 images .* "
                                         r"these are not posed: photo_1.png, photo_4.png"):
        process_capture(photos, tmp_path / "out2", masks=masks, min_mask_agreement=0.0, escalate=False, progress=False,
                        min_registered=0.9)


@needs_pycolmap
@pytest.mark.parametrize("second_refused", [False, True])
def test_a_model_the_pose_checks_refuse_is_posed_again_and_never_kept_over_one_they_pass(tmp_path, monkeypatch, caplog, second_refused):
    import nerf_lightning.capture.posing as posing
    from nerf_lightning.capture import process_capture

    photos = object_photos(tmp_path / "photos", count=6)
    masks = save_masks(tmp_path / "masks", photos)
    calls = []

    wrong = {**NOTHING_FOUND, "camera_spread": 48.0, "refuse": ["the posed cameras lie 48 times farther apart than they are from what "
                                                                "they see; so the photos are strung together in the wrong places"]}
    found = [wrong, wrong if second_refused else dict(NOTHING_FOUND)]
    monkeypatch.setattr(posing, "reconstruct", stand_in_reconstruct(calls))  # every photo registers both times
    monkeypatch.setattr(posing, "pose_checks", lambda *_: found.pop(0))
    monkeypatch.setattr(posing, "silhouette_agreement", masks_agree)
    if second_refused:
        with pytest.raises(ValueError, match="COLMAP registered 6 images of .*, but its model is wrong: the posed cameras lie 48 times"):
            process_capture(photos, tmp_path / "out", masks=masks, min_mask_agreement=0.0, progress=False)
        assert len(calls) == 2 and not (tmp_path / "out" / "transforms.json").exists()
        return
    report = process_capture(photos, tmp_path / "out", masks=masks, min_mask_agreement=0.0, progress=False)
    assert len(calls) == 2 and calls[1]["strong"] and report["escalated"]["why"] == "model" and report["escalated"]["kept"] == "stronger"
    assert "COLMAP's model is wrong: the posed cameras lie 48 times farther apart than they are from what they see (" in caplog.text
    assert report["pose_checks"]["refuse"] == [] and report["registered"] == 6


def test_the_stronger_pass_matches_every_pair_of_few_photos_and_the_pairs_that_can_overlap_of_many():
    from nerf_lightning.capture.posing import stronger_matcher

    assert stronger_matcher(6) == stronger_matcher(25) == "exhaustive"  # 300 pairs
    assert stronger_matcher(26) == stronger_matcher(66) == "overlapping"  # 325 and 2,145 pairs


def test_the_model_kept_is_the_one_with_more_photos_posed_weighted_by_the_masks_agreement():
    from nerf_lightning.capture.posing import model_score

    def agreeing(value):
        return {"median_coverage": value}

    photos = lambda count: {f"p{index}" for index in range(count)}
    assert model_score(photos(59), agreeing(0.95), True) > model_score(photos(59), agreeing(0.79), True)
    assert model_score(photos(55), agreeing(0.95), True) > model_score(photos(59), agreeing(0.6), True)
    # a model of under 3 photos is never kept over one of 3 or more, however little its masks agree
    assert model_score(photos(3), agreeing(0.0), True) > model_score(photos(2), None, True)
    # equal weights (both wrong: 0 %): the one with more photos posed, which the masks' check then names
    assert model_score(photos(15), agreeing(0.0), True) > model_score(photos(4), agreeing(0.0), True)
    # without masks, the count alone, as before
    assert model_score(photos(6), None, False) > model_score(photos(5), None, False)


@needs_pycolmap
@pytest.mark.parametrize("agreements, kept", [((0.95,), None), ((0.6, 0.95), "stronger"), ((0.6, 0.5), "first")])
def test_a_model_the_masks_agree_with_too_little_is_posed_again_and_the_better_kept(tmp_path, monkeypatch, agreements, kept):
    # every photo registers each time, but the masks' agreement with the first model's poses says it is wrong in part
    # (as on moldGoldCape's darkened photos): under ESCALATE_AGREEMENT it is posed again, and the model whose masks
    # agree more is kept
    import nerf_lightning.capture.posing as posing
    from nerf_lightning.capture import format_report, process_capture

    photos = object_photos(tmp_path / "photos", count=6)
    masks = save_masks(tmp_path / "masks", photos)
    calls, left = [], list(agreements)

    def silhouette_agreement(transforms, points, staging, downscales, seed=0):
        return {"median_coverage": left.pop(0), "views_below": [], "coverage": {}, "masks_read": "masks"}

    monkeypatch.setattr(posing, "reconstruct", stand_in_reconstruct(calls))
    monkeypatch.setattr(posing, "pose_checks", lambda *_: dict(NOTHING_FOUND))
    monkeypatch.setattr(posing, "silhouette_agreement", silhouette_agreement)
    report = process_capture(photos, tmp_path / "out", masks=masks, min_mask_agreement=0.4, progress=False)
    assert left == [] and report["registered"] == 6
    if kept is None:
        assert len(calls) == 1 and "escalated" not in report and report["silhouettes"]["median_coverage"] == 0.95
        return
    escalated = report["escalated"]
    assert len(calls) == 2 and calls[1]["strong"] and escalated["why"] == "masks" and escalated["kept"] == kept
    assert (escalated["mask_agreement_before"], escalated["mask_agreement_after"]) == agreements
    assert report["silhouettes"]["median_coverage"] == (agreements[1] if kept == "stronger" else agreements[0])
    assert "the masks agreed 60% at first: posed again with stronger settings" in format_report(report)
    assert ("that model is kept" if kept == "stronger" else "the first model is kept") in format_report(report)


def test_stronger_settings_read_features_at_up_to_twice_max_size_but_not_past_the_photos():
    from nerf_lightning.capture.posing import escalated_settings

    assert escalated_settings(1600, 8192, {"a": (4000, 4000)}) == {"max_size": 3200, "max_features": 8192, "strong": True}
    assert escalated_settings(1600, 8192, {"a": (2400, 1800)})["max_size"] == 2400
    assert escalated_settings(1600, 8192, {"a": (912, 912)})["max_size"] == 1600


@pytest.mark.parametrize(("side", "expected"), [
    (1824, " data.scene.downscale=2 data.patch_size=384"),  # moldGoldCape's photos: 912 px, on patches
    (4000, " data.scene.downscale=4 data.patch_size=384"),  # a 4000 px turntable: 1000 px
    (9000, " data.scene.downscale=9 data.patch_size=384"),  # any whole factor: the loader averages the full photos
    (800, " data.scene.downscale=1 data.patch_size=384"),
    (480, " data.scene.downscale=1"),  # small enough to train on whole views
    (None, ""),  # a report written before the photos' side was kept: the presets' own downscale
])
def test_next_commands_size_a_masked_capture_for_the_object_presets(side, expected):
    from nerf_lightning.capture.report import next_commands

    report = {"output": "out", "masks": {"count": 3}, **({"photo_side": side} if side else {})}
    assert next_commands(report) == [
        f"next: nerf-train experiment=splat_object_cpu data.root=out{expected}",
        "  or a NeRF of the object in its box: nerf-train experiment=nerfacto_object_cpu data.root=out"
        + expected.replace(" data.patch_size=384", "")]
    assert next_commands({"output": "out", "photo_side": 1824}) == ["next: nerf-train experiment=fast_unbounded data.root=out"]
