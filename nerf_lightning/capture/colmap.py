"""COLMAP's database of a capture, run in-process through ``pycolmap`` (the ``colmap`` extra: its wheel carries
COLMAP, nothing else to install): features and matches, the first two of structure from motion's three stages (the
mapping and the result as a ``transforms.json``: :mod:`~nerf_lightning.capture.reconstruction`).

Each stage has a progress bar: SIFT features of every image (read at most ``max_size`` pixels on their long side; the
keypoints come back in the full image's pixels, so the cameras are those of the images as written), and matching
with geometric verification of the chosen image pairs (every pair; or, for a video or a long capture, each image with
its neighbours in time and with the images that look most like it). Features and matches are fed in chunks so that
the bars move: images by the handful, pairs by the block.

Masks, where given, keep each image's features to its object: COLMAP reads ``<masks>/<image name>.png`` (``IMG_1.jpg``'s
is ``IMG_1.jpg.png``; an image without one is skipped, not extracted unmasked) at full size, grey, and drops the
keypoints on its zero pixels after scaling them back from the ``max_size`` copy to full-size pixels, so one
full-size mask serves any ``max_size`` (a mask of another size is not scaled: it is read pixel for pixel against
the full-size keypoints, so the capture's intake checks sizes first).

Written against pycolmap 4.2 (``FeatureExtractionOptions``, ``match_image_pairs``).
"""

from __future__ import annotations

import contextlib
import os
from collections.abc import Iterable, Iterator, Sequence
from pathlib import Path
from typing import Any

import numpy as np
import torch
from tqdm import tqdm

from nerf_lightning.capture.choices import COLMAP_EXTRA, MATCHERS
from nerf_lightning.capture.images import exif_focal_length, natural_key
from nerf_lightning.capture.retrieval import retrieved_pairs
from nerf_lightning.errors import MissingExtraError

# exhaustive matching costs n^2 / 2 pairs: beyond this many images ``auto`` matches neighbours in name order
EXHAUSTIVE_UP_TO = 100
# sequential matching's loop closures: each image also with the images this many that look most like it
LOOP_NEIGHBOURS = 8
# overlapping matching (the stronger pass's): each image with this many next in name order, round the ring
OVERLAP_NEIGHBOURS = 3


def import_pycolmap() -> Any:
    """The ``pycolmap`` module; MissingExtraError with the install line when it is not installed."""
    try:
        import pycolmap
    except ImportError:
        raise MissingExtraError(f"camera poses need pycolmap, the colmap extra: {COLMAP_EXTRA}") from None
    return pycolmap


@contextlib.contextmanager
def colmap_log(verbose: bool) -> Iterator[None]:
    """COLMAP's own log (glog, on stderr) while inside: everything when ``verbose``, else errors only."""
    logging = import_pycolmap().logging
    before = logging.minloglevel
    logging.minloglevel = 0 if verbose else 2
    try:
        yield
    finally:
        logging.minloglevel = before


def chunks(items: Sequence, size: int) -> Iterator[Sequence]:
    for start in range(0, len(items), size):
        yield items[start : start + size]


def exhaustive_pairs(count: int, block: int = 10) -> list[list[tuple[int, int]]]:
    """Every pair (i, j), i < j, of ``count`` images, in chunks of one block of images against another, so that each
    chunk reads the features of at most 2 ``block`` images."""
    starts = range(0, count, block)
    return [[(i, j) for i in range(a, min(a + block, count)) for j in range(max(b, i + 1), min(b + block, count))]
            for a in starts for b in starts if b >= a]


def sequential_pairs(count: int, overlap: int = 10, chunk: int = 100, loops: Iterable[tuple[int, int]] = ()) -> list[list[tuple[int, int]]]:
    """Each image with the next ``overlap`` ones and with those 2, 4, 8, ... 2^(overlap - 1) ahead (COLMAP's sequential
    matcher with quadratic overlap), and the ``loops`` pairs (i, j), i < j, besides: the loop closures COLMAP's
    sequential matcher finds with a vocabulary tree (:func:`loop_closure_pairs`); in chunks of ``chunk``."""
    pairs = {(i, i + step) for i in range(count) for step in [*range(1, overlap + 1), *(2**k for k in range(overlap))] if i + step < count}
    pairs = sorted(pairs | set(loops))
    return [pairs[start : start + chunk] for start in range(0, len(pairs), chunk)]


def overlapping_pairs(database: Path, names: Sequence[str], verified_in: Path | None = None, neighbours: int = OVERLAP_NEIGHBOURS,
                      retrieved: int = LOOP_NEIGHBOURS, seed: int = 0, chunk: int = 50) -> list[list[tuple[int, int]]]:
    """The pairs of ``names`` that can overlap, not every pair: each image with the ``neighbours`` next in name order,
    round the end to the start (a turntable's or an orbit's photos, taken in order, close their ring), with the
    ``retrieved`` images of ``database`` that look most like it (:func:`loop_closure_pairs`: photos out of order, a
    second ring), and with those it verified a geometry with in ``verified_in`` (a first pass's database); in chunks
    of ``chunk``, so that the progress bar and its time left move often. About (neighbours + retrieved) x count
    pairs instead of count^2 / 2."""
    count = len(names)
    pairs = {(min(i, (i + step) % count), max(i, (i + step) % count)) for i in range(count) for step in range(1, neighbours + 1)
             if (i + step) % count != i}
    pairs |= loop_closure_pairs(database, names, neighbours=retrieved, seed=seed)
    if verified_in is not None:
        pycolmap = import_pycolmap()
        place = {name: k for k, name in enumerate(names)}
        with contextlib.closing(pycolmap.Database.open(verified_in)) as opened:
            index = {image.image_id: place[image.name] for image in opened.read_all_images() if image.name in place}
            pair_ids, inliers = opened.read_two_view_geometry_num_inliers()
        for pair_id, verified in zip(pair_ids, inliers):
            first, second = pycolmap.pair_id_to_image_pair(pair_id)
            if verified > 0 and first in index and second in index:
                pairs.add((min(index[first], index[second]), max(index[first], index[second])))
    pairs = sorted(pairs)
    return [pairs[start : start + chunk] for start in range(0, len(pairs), chunk)]


def loop_closure_pairs(database: Path, names: Sequence[str], neighbours: int = LOOP_NEIGHBOURS, seed: int = 0) -> set[tuple[int, int]]:
    """Each of ``names`` paired with the ``neighbours`` images of ``database`` that look most like it by their SIFT
    descriptors (:func:`nerf_lightning.capture.retrieval.retrieved_pairs`): (i, j), i < j, indices into ``names``."""
    pycolmap = import_pycolmap()
    with contextlib.closing(pycolmap.Database.open(database)) as opened:
        ids = {image.name: image.image_id for image in opened.read_all_images()}
        # an image without features (none inside its mask) is paired by chance, which costs a few pairs and no model
        descriptors = [torch.from_numpy(np.array(opened.read_descriptors(ids[name]).data).reshape(-1, 128)) if name in ids
                       else torch.zeros(0, 128, dtype=torch.uint8)
                       for name in names]
    return retrieved_pairs(descriptors, neighbours, seed=seed)


def choose_matcher(matcher: str, count: int, from_video: bool) -> str:
    """``exhaustive`` or ``sequential``: ``auto`` matches every pair of photos under ``EXHAUSTIVE_UP_TO`` images and
    neighbours in time, with loop closures, for a video's frames and for larger sets."""
    if matcher not in MATCHERS:
        raise ValueError(f"matcher must be one of {', '.join(MATCHERS)}, got '{matcher}'")
    if matcher != "auto":
        return matcher
    return "sequential" if from_video or count >= EXHAUSTIVE_UP_TO else "exhaustive"


def extract_features(database: Path, images: Path, names: Sequence[str], camera_model: str, single_camera: bool,
                     max_size: int, max_features: int, progress: bool, masks: Path | None = None,
                     strong: bool = False) -> list[dict[str, Any]]:
    """SIFT keypoints and descriptors of ``images/<name>`` for each name into the COLMAP ``database``; the cameras
    (one shared, or one an image) of ``camera_model`` with a focal length from EXIF (:func:`correct_focal_priors`,
    whose changes are returned) or 1.2 x the long side. With ``masks``, only the keypoints on a non-zero pixel of
    ``masks/<name>.png`` (full size, grey) are kept. ``strong``: SIFT with affine shape estimation and domain-size
    pooling (COLMAP's options for wide baselines and shiny, weakly textured subjects; slower)."""
    pycolmap = import_pycolmap()
    reader = pycolmap.ImageReaderOptions()
    reader.camera_model = camera_model
    if masks is not None:
        absent = [name for name in names if not (masks / f"{name}.png").is_file()]
        if absent:  # COLMAP would skip those images with a log line and leave them out of the model
            raise ValueError(f"no COLMAP mask {masks / (absent[0] + '.png')} for {absent[0]} ({len(absent)} missing)")
        reader.mask_path = masks
    extraction = pycolmap.FeatureExtractionOptions()
    extraction.max_image_size = max_size
    extraction.sift.max_num_features = max_features
    extraction.sift.estimate_affine_shape = extraction.sift.domain_size_pooling = strong
    mode = pycolmap.CameraMode.SINGLE if single_camera else pycolmap.CameraMode.PER_IMAGE
    # the images and their cameras written first, numbered in the names' sorted order (COLMAP sorts them byte by
    # byte): the extraction keeps an image's id where it finds it, and otherwise numbers the images in the order its
    # threads finish them, so that the same photos were matched, mapped and triangulated in another order from run to
    # run (a test turntable's points: 4 runs in 160 lost up to 3 % of them). The cameras written here, one shared or
    # one an image, are those the chunks' images then find. It reads each photo once more (about 2 s for 59 photos of
    # 1824 px on 2 cores)
    with contextlib.closing(pycolmap.Database.open(database)):
        pass  # import_images needs the database file to exist
    pycolmap.import_images(database, images, camera_mode=mode, image_names=list(names), options=reader)
    with tqdm(total=len(names), desc="features", unit="image", disable=not progress) as bar:
        for chunk in chunks(names, max(4, 2 * (os.cpu_count() or 1))):
            pycolmap.extract_features(database, images, image_names=list(chunk), camera_mode=mode, reader_options=reader,
                                      extraction_options=extraction)
            bar.update(len(chunk))
    changed = correct_focal_priors(database, images)
    if camera_model in VERIFIED_CALIBRATED_ONLY:
        assume_focal_priors(database)
    return changed


# lens models whose two-view geometries COLMAP verifies only as calibrated (an essential matrix on the undistorted
# rays: a fundamental matrix needs a pinhole's straight lines); without a prior focal length it verifies no pair at all
# (the fisheye turntable of tests/capture/test_fisheye_posing.py: 0 of 630 pairs)
VERIFIED_CALIBRATED_ONLY = ("OPENCV_FISHEYE",)


def assume_focal_priors(database: Path) -> None:
    """Each camera of ``database`` without a prior focal length (no EXIF) takes COLMAP's guess, 1.2 x the image's
    long side, as one, so that its pairs are verified as calibrated; the bundle adjustments refine it as they refine
    any focal length (the fisheye turntable of 320 px: 198 px came out within 0.5 % from a guess of 384)."""
    pycolmap = import_pycolmap()
    with contextlib.closing(pycolmap.Database.open(database)) as opened:
        for camera in opened.read_all_cameras():
            if not camera.has_prior_focal_length:
                camera.has_prior_focal_length = True
                opened.update_camera(camera)


# a camera's focal length from EXIF is replaced by this project's reading where the two differ by more than this
FOCAL_PRIOR_TOLERANCE = 0.05


def correct_focal_priors(database: Path, images: Path) -> list[dict[str, Any]]:
    """Each camera of ``database`` given the focal length of its first image's EXIF read for the image as it is
    (:func:`~nerf_lightning.capture.images.exif_focal_length`) where COLMAP's own reading differs from it by more
    than :data:`FOCAL_PRIOR_TOLERANCE`: COLMAP takes a downscaled or cropped photo's EXIF as if for its full frame
    (on moldGoldCape's 912 px copies 7558 px instead of 1890, and its incremental mapper then registered 2 of 59;
    the two-view geometries, checked as calibrated, suffer too). Before matching, so that the matches are verified
    with the right camera. Returns what was changed: camera, image, COLMAP's focal length and the one set."""
    pycolmap = import_pycolmap()
    changed = []
    with contextlib.closing(pycolmap.Database.open(database)) as opened:
        first_images = {}
        for image in sorted(opened.read_all_images(), key=lambda image: natural_key(image.name)):
            first_images.setdefault(image.camera_id, image.name)
        for camera in opened.read_all_cameras():
            name = first_images.get(camera.camera_id)
            focal = exif_focal_length(images / name) if name is not None else None
            if focal is None or abs(focal - camera.mean_focal_length()) <= FOCAL_PRIOR_TOLERANCE * focal:
                continue
            changed.append({"camera": int(camera.camera_id), "image": name, "colmap_px": round(camera.mean_focal_length(), 1),
                            "set_px": round(focal, 1)})
            params = np.array(camera.params)
            params[list(camera.focal_length_idxs())] = focal
            camera.params = params
            camera.has_prior_focal_length = True
            opened.update_camera(camera)
    return changed


def match_features(database: Path, names: Sequence[str], pairs: list[list[tuple[int, int]]], scratch: Path, seed: int, progress: bool,
                   guided: bool = False) -> None:
    """Match the features of each pair of images (indices into ``names``) and keep the matches that fit a two-view
    geometry (fundamental, essential or homography matrix, RANSAC seeded with ``seed``), chunk by chunk through pair
    lists in ``scratch``. ``guided``: a second round of matching guided by each pair's verified geometry."""
    pycolmap = import_pycolmap()
    matching = pycolmap.FeatureMatchingOptions()
    matching.guided_matching = guided
    scratch.mkdir(parents=True, exist_ok=True)
    pairing = pycolmap.ImportedPairingOptions()
    pairing.match_list_path = scratch / "pairs.txt"
    verification = pycolmap.TwoViewGeometryOptions()
    verification.ransac.random_seed = seed  # unseeded, the verified matches and so the model differ from run to run
    with tqdm(total=sum(map(len, pairs)), desc="matching", unit="pair", disable=not progress) as bar:
        for chunk in pairs:
            pairing.match_list_path.write_text("".join(f"{names[i]} {names[j]}\n" for i, j in chunk))
            pycolmap.match_image_pairs(database, matching_options=matching, pairing_options=pairing, verification_options=verification)
            bar.update(len(chunk))


def database_statistics(database: Path) -> dict[str, float]:
    """What each stage left in the matched ``database``, to say where a capture is lost: the keypoints an image (mean
    and fewest: with masks, those on the object), the pairs matched, the pairs geometrically verified, and the mean
    inlier matches a verified pair."""
    pycolmap = import_pycolmap()
    with contextlib.closing(pycolmap.Database.open(database)) as opened:
        keypoints = [opened.num_keypoints_for_image(image.image_id) for image in opened.read_all_images()]
        pair_ids, inliers = opened.read_two_view_geometry_num_inliers()
        verified = [count for count in inliers if count > 0]
        return {"keypoints_mean": float(np.mean(keypoints)) if keypoints else 0.0, "keypoints_min": int(min(keypoints, default=0)),
                "pairs_matched": int(opened.num_matched_image_pairs()), "pairs_verified": len(verified),
                "inliers_per_verified_pair": float(np.mean(verified)) if verified else 0.0}


def verified_pairs(opened: Any, registered: set[int]) -> Iterator[tuple[int, int, Any]]:
    """The geometrically verified pairs of an opened COLMAP database between ``registered`` image ids, as (first id,
    second id, two-view geometry) for those with inlier matches."""
    pycolmap = import_pycolmap()
    pair_ids, geometries = opened.read_two_view_geometries()
    for pair_id, geometry in zip(pair_ids, geometries):
        first, second = pycolmap.pair_id_to_image_pair(pair_id)
        if first in registered and second in registered and len(geometry.inlier_matches) > 0:
            yield first, second, geometry
