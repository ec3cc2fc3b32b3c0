"""Camera poses of a capture by COLMAP's structure from motion, run in-process through ``pycolmap`` (the ``colmap``
extra: its wheel carries COLMAP, nothing else to install), and the result as a nerfstudio ``transforms.json``.

Three stages, each with a progress bar: SIFT features of every image (read at most ``max_size`` pixels on their long
side; the keypoints come back in the full image's pixels, so the cameras are those of the images as written),
matching with geometric verification of the chosen image pairs (every pair; or, for a video or a long capture, each
image with its neighbours in time and with the images that look most like it), and mapping. Features and matches
are fed in chunks so that the bars move: images by the handful, pairs by the block.

Masks, where given, keep each image's features to its object: COLMAP reads ``<masks>/<image name>.png`` (``IMG_1.jpg``'s
is ``IMG_1.jpg.png``; an image without one is skipped, not extracted unmasked) at full size, grey, and drops the
keypoints on its zero pixels after scaling them back from the ``max_size`` copy to full-size pixels, so one
full-size mask serves any ``max_size`` (a mask of another size is not scaled: it is read pixel for pixel against
the full-size keypoints, so process.py checks sizes first).

Mapping runs both COLMAP mappers by default, the global one (GLOMAP) and the incremental one, and keeps the model that
explains the most geometrically verified matches. A model can reproject its own points to a pixel and still be
wrong: on fox's 50 photos (two arcs of a walk round a mounted fox before a repeating rose wallpaper, the photos between
them missing) either mapper, depending on the matches' RANSAC seed, joins the second arc to the first through
wallpaper matches one repeat off, every image registered and the arcs misplaced; such a model contradicts the
fox's own matches between the arcs, which the right one explains (docs/benchmarks.md, "Both COLMAP mappers").

Written against pycolmap 4.2 (``FeatureExtractionOptions``, ``Image.cam_from_world()``, ``match_image_pairs``,
``global_mapping``).
"""

from __future__ import annotations

import contextlib
import os
import shutil
import time
from collections.abc import Iterable, Iterator, Sequence
from pathlib import Path
from typing import Any

import numpy as np
import torch
from tqdm import tqdm

from nerf_lightning.capture.choices import CAMERA_MODELS, CAMERA_PARAMETERS, COLMAP_EXTRA, MAPPERS, MATCHERS  # noqa: F401 (also read from here)
from nerf_lightning.capture.images import exif_focal_length, mask_name, natural_key
from nerf_lightning.capture.retrieval import retrieved_pairs
from nerf_lightning.errors import MissingExtraError
from nerf_lightning.geometry.cameras import opengl_to_opencv

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
    return correct_focal_priors(database, images)


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


def map_images(database: Path, images: Path, scratch: Path, count: int, mapper: str, seed: int, progress: bool) -> list[Any]:
    """Camera poses and 3D points from the matched ``database``: every model the mapper builds (models of fewer than
    3 images dropped), largest first.

    ``global`` is COLMAP's global mapper (GLOMAP: all rotations averaged at once, then positions and points placed
    jointly); ``incremental`` is COLMAP's classic mapper, which registers one image at a time from an initial pair.
    """
    pycolmap = import_pycolmap()
    pycolmap.set_random_seed(seed)
    scratch.mkdir(parents=True, exist_ok=True)
    with tqdm(total=count, desc=f"mapping ({mapper})", unit="image", disable=not progress) as bar:
        if mapper == "global":
            if not hasattr(pycolmap, "global_mapping"):
                raise ValueError(f"mapper=global needs pycolmap 4.2 or later (installed: {pycolmap.__version__}); "
                                 f"upgrade it ({COLMAP_EXTRA}) or use mapper=incremental")
            options = pycolmap.GlobalPipelineOptions()
            options.min_model_size = 3
            options.random_seed = seed
            models = pycolmap.global_mapping(database, images, scratch, options=options)
        else:
            options = pycolmap.IncrementalPipelineOptions()
            options.min_model_size = 3
            options.random_seed = seed

            def registered(newly: int) -> None:
                bar.update(min(newly, bar.total - bar.n))

            models = pycolmap.incremental_mapping(database, images, scratch, options=options, initial_image_pair_callback=lambda: registered(2),
                                                  next_image_callback=lambda: registered(1))
        models = sorted(models.values(), key=lambda model: model.num_reg_images(), reverse=True)
        bar.n = models[0].num_reg_images() if models else 0  # the largest model's, where several were built
        bar.refresh()
    return models


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


def sampson_distance(cam1_from_world: np.ndarray, cam2_from_world: np.ndarray, points1: np.ndarray, points2: np.ndarray) -> np.ndarray:
    """How far matched points are from satisfying the epipolar constraint of two posed cameras (first-order geometric
    distance, in normalised image coordinates: multiply by a focal length for pixels).

    Args:
        cam1_from_world, cam2_from_world: (3, 4) world-to-camera matrices [R | t].
        points1, points2: (M, 2) matched points in normalised camera coordinates (lens undone).
    Returns:
        (M,) Sampson distances.
    """
    rotation = cam2_from_world[:, :3] @ cam1_from_world[:, :3].T
    x, y, z = cam2_from_world[:, 3] - rotation @ cam1_from_world[:, 3]
    essential = np.array([[0.0, -z, y], [z, 0.0, -x], [-y, x, 0.0]]) @ rotation
    homogeneous1 = np.concatenate([points1, np.ones((len(points1), 1))], axis=1)
    homogeneous2 = np.concatenate([points2, np.ones((len(points2), 1))], axis=1)
    line2, line1 = homogeneous1 @ essential.T, homogeneous2 @ essential
    numerator = (homogeneous2 * line2).sum(1) ** 2
    denominator = line2[:, 0] ** 2 + line2[:, 1] ** 2 + line1[:, 0] ** 2 + line1[:, 1] ** 2
    return np.sqrt(numerator / np.maximum(denominator, 1e-30))


def verified_pairs(opened: Any, registered: set[int]) -> Iterator[tuple[int, int, Any]]:
    """The geometrically verified pairs of an opened COLMAP database between ``registered`` image ids, as (first id,
    second id, two-view geometry) for those with inlier matches."""
    pycolmap = import_pycolmap()
    pair_ids, geometries = opened.read_two_view_geometries()
    for pair_id, geometry in zip(pair_ids, geometries):
        first, second = pycolmap.pair_id_to_image_pair(pair_id)
        if first in registered and second in registered and len(geometry.inlier_matches) > 0:
            yield first, second, geometry


def verified_matches_explained(database: Path, reconstruction: Any, threshold_px: float = 4.0) -> tuple[int, int]:
    """How many of the geometrically verified matches between registered images the model's poses explain, of how
    many: a pair whose inliers lie within ``threshold_px`` (median Sampson distance) of the epipolar geometry of its
    two posed cameras counts with all its inliers.

    A model can reproject its own points well and still be wrong: joined through a repeating pattern one repeat off,
    it explains the pattern's matches and contradicts the other pairs'. This counts those pairs, without ground truth.
    """
    pycolmap = import_pycolmap()
    registered = set(reconstruction.reg_image_ids())
    explained = total = 0
    with contextlib.closing(pycolmap.Database.open(database)) as opened:
        keypoints = {image_id: opened.read_keypoints(image_id)[:, :2] for image_id in registered}
        for first, second, geometry in verified_pairs(opened, registered):
            inliers = geometry.inlier_matches
            image1, image2 = reconstruction.image(first), reconstruction.image(second)
            camera1, camera2 = reconstruction.camera(image1.camera_id), reconstruction.camera(image2.camera_id)
            points1 = camera1.cam_from_img(keypoints[first][inliers[:, 0]])
            points2 = camera2.cam_from_img(keypoints[second][inliers[:, 1]])
            distance = sampson_distance(camera_from_world(image1)[:3], camera_from_world(image2)[:3], points1, points2)
            focal = 0.5 * (camera1.mean_focal_length() + camera2.mean_focal_length())
            total += len(inliers)
            explained += len(inliers) if float(np.median(distance)) * focal < threshold_px else 0
    return explained, total


def reconstruct(images: Path, names: Sequence[str], colmap_dir: Path, *, matcher: str, mapper: str = "auto", camera_model: str = "OPENCV",
                single_camera: bool = True, max_size: int = 1600, max_features: int = 8192, seed: int = 0, masks: Path | None = None,
                progress: bool = True, verbose: bool = False, strong: bool = False,
                verified_in: Path | None = None) -> tuple[Any | None, dict[str, float], dict[str, Any]]:
    """Structure from motion of ``images/<name>`` for each name: ``colmap_dir/database.db`` and the chosen model,
    also written to ``colmap_dir/sparse/0`` (COLMAP's binary format).

    Args:
        matcher: ``exhaustive`` or ``sequential`` (see :func:`choose_matcher`), or ``overlapping``
            (:func:`overlapping_pairs`, with the pairs ``verified_in`` a first pass's database: the stronger pass's).
        mapper: ``global``, ``incremental`` (see :func:`map_images`) or ``auto``: both, and the model that explains
            the most verified matches kept (:func:`verified_matches_explained`).
        camera_model: one of :data:`CAMERA_MODELS`.
        single_camera: one camera (intrinsics) shared by every image, as for photos from one phone at one zoom.
        max_size: the long side, in pixels, images are read at for feature extraction.
        max_features: SIFT features kept an image.
        masks: a folder of COLMAP's masks, ``<name>.png`` for each name (0 where features are dropped), or None.
        strong: the stronger settings: SIFT with affine shapes and domain-size pooling, and guided matching.
    Returns:
        the model (a ``pycolmap.Reconstruction``, the largest its mapper built; None when none was built), the seconds
        each stage took, and of each mapper run its images registered and fraction of verified matches explained
        (``mappers``), which was kept (``mapper``), and what features and matching left (``matches``,
        :func:`database_statistics`), and the cameras whose EXIF focal length was corrected (``focal_priors``,
        :func:`correct_focal_priors`), and the other mapper's model (``other_model``; None where only one built a
        model), which :func:`~nerf_lightning.capture.model_checks.pose_checks` compares the kept one with.
    """
    if camera_model not in CAMERA_MODELS:
        raise ValueError(f"camera_model must be one of {', '.join(CAMERA_MODELS)} (models whose lenses the transforms.json "
                         f"loader can undo), got '{camera_model}'")
    if mapper not in MAPPERS:
        raise ValueError(f"mapper must be one of {', '.join(MAPPERS)}, got '{mapper}'")
    if matcher not in ("exhaustive", "sequential", "overlapping"):
        raise ValueError(f"reconstruct: matcher must be exhaustive, sequential or overlapping, got '{matcher}'")
    colmap_dir.mkdir(parents=True, exist_ok=True)
    database = colmap_dir / "database.db"
    seconds = {}
    with colmap_log(verbose):
        started = time.perf_counter()
        focal_priors = extract_features(database, images, names, camera_model, single_camera, max_size, max_features, progress, masks=masks,
                                        strong=strong)
        seconds["features"] = time.perf_counter() - started

        started = time.perf_counter()
        if matcher == "exhaustive":
            pairs = exhaustive_pairs(len(names))
        elif matcher == "overlapping":
            pairs = overlapping_pairs(database, names, verified_in, seed=seed)
        else:
            pairs = sequential_pairs(len(names), loops=loop_closure_pairs(database, names, seed=seed))
        match_features(database, names, pairs, colmap_dir / "pairs", seed, progress, guided=strong)
        seconds["matching"] = time.perf_counter() - started
        matched = database_statistics(database)

        started = time.perf_counter()
        candidates, tried = {}, {}
        for name in ("global", "incremental") if mapper == "auto" else (mapper,):
            models = map_images(database, images, colmap_dir / f"models_{name}", len(names), name, seed, progress)
            if models:
                explained, total = verified_matches_explained(database, models[0])
                candidates[name] = (explained, models[0])
                tried[name] = {"registered": models[0].num_reg_images(), "verified_matches_explained": round(explained / max(total, 1), 4)}
            else:
                tried[name] = {"registered": 0, "verified_matches_explained": 0.0}
        seconds["mapping"] = time.perf_counter() - started
    shutil.rmtree(colmap_dir / "pairs", ignore_errors=True)
    for name in tried:
        shutil.rmtree(colmap_dir / f"models_{name}", ignore_errors=True)
    if not candidates:
        return None, seconds, {"mapper": None, "mappers": tried, "matches": matched, "focal_priors": focal_priors, "other_model": None}
    kept = max(candidates, key=lambda name: candidates[name][0])
    model = candidates[kept][1]
    (colmap_dir / "sparse" / "0").mkdir(parents=True, exist_ok=True)
    model.write(colmap_dir / "sparse" / "0")
    other = next((candidate for name, (_, candidate) in candidates.items() if name != kept), None)
    return model, seconds, {"mapper": kept, "mappers": tried, "matches": matched, "focal_priors": focal_priors, "other_model": other}


def camera_intrinsics(camera: Any) -> dict[str, Any]:
    """A COLMAP camera as transforms.json keys: ``camera_model``, ``fl_x``, ``fl_y``, ``cx``, ``cy``, ``k1``, ``k2``,
    ``p1``, ``p2`` (zero where the model has no such term), ``w``, ``h``, in the pixels of the images it saw."""
    model = camera.model.name
    if model not in CAMERA_PARAMETERS:
        raise ValueError(f"COLMAP camera model {model} is not one the transforms.json loader reads ({', '.join(CAMERA_MODELS)})")
    values = dict(zip(CAMERA_PARAMETERS[model], (float(value) for value in camera.params)))
    if "f" in values:
        values["fl_x"] = values["fl_y"] = values.pop("f")
    keys = {"camera_model": model, "fl_x": values["fl_x"], "fl_y": values["fl_y"], "cx": values["cx"], "cy": values["cy"]}
    keys.update({key: values.get(key, 0.0) for key in ("k1", "k2", "p1", "p2")})
    keys.update({"w": int(camera.width), "h": int(camera.height)})
    return keys


def camera_from_world(image: Any) -> np.ndarray:
    """(4, 4) world-to-camera matrix (OpenCV camera axes) of a registered COLMAP image."""
    pose = image.cam_from_world
    pose = pose() if callable(pose) else pose  # a method since pycolmap 3.12 (rigs), a property before
    w2c = np.eye(4)
    w2c[:3] = pose.matrix()
    return w2c


def reconstruction_to_transforms(reconstruction: Any, image_folder: str = "images", mask_folder: str | None = None,
                                 only: set[str] | None = None) -> dict[str, Any]:
    """A COLMAP model as a nerfstudio ``transforms.json`` dict, registered images in name order.

    Each frame's ``transform_matrix`` is its OpenGL camera-to-world (x right, y up, looking down -z): the inverse of
    COLMAP's world-to-camera with the camera's y and z axes flipped, in COLMAP's world coordinates (no axes swapped;
    the loader centres, orients and scales the world itself). Intrinsics are global keys when the images share one
    camera, per-frame keys otherwise. ``only``: the names of the registered images to write (None: all). ``ply_file_path``
    names the sparse points, written beside it. With
    ``mask_folder``, each frame's ``mask_path`` (nerfstudio's key) names ``<mask_folder>/<image stem>.png``.
    """
    images = sorted((reconstruction.image(image_id) for image_id in reconstruction.reg_image_ids()
                     if only is None or reconstruction.image(image_id).name in only), key=lambda image: natural_key(image.name))
    cameras = {image.camera_id for image in images}
    meta: dict[str, Any] = camera_intrinsics(reconstruction.camera(next(iter(cameras)))) if len(cameras) == 1 else {}
    frames = []
    for image in images:
        c2w = opengl_to_opencv(torch.linalg.inv(torch.from_numpy(camera_from_world(image))))  # its own inverse: OpenCV -> OpenGL too
        frame = {"file_path": f"{image_folder}/{image.name}", "transform_matrix": c2w.tolist(), "colmap_im_id": int(image.image_id)}
        if mask_folder is not None:
            frame["mask_path"] = f"{mask_folder}/{mask_name(image.name)}"
        if len(cameras) > 1:
            frame.update(camera_intrinsics(reconstruction.camera(image.camera_id)))
        frames.append(frame)
    meta["frames"] = frames
    meta["ply_file_path"] = "sparse_pc.ply"
    return meta


def sparse_points(reconstruction: Any) -> tuple[np.ndarray, np.ndarray]:
    """The model's 3D points: (P, 3) float64 positions in its world and (P, 3) uint8 RGB colours."""
    points = list(reconstruction.points3D.values())
    if not points:
        return np.zeros((0, 3)), np.zeros((0, 3), dtype=np.uint8)
    return np.stack([point.xyz for point in points]), np.stack([point.color for point in points]).astype(np.uint8)


def model_statistics(reconstruction: Any) -> dict[str, float]:
    """What says how good a model is: mean reprojection error (pixels), mean track length (images a 3D point is
    seen in), mean observations a registered image, and the number of 3D points."""
    return {
        "mean_reprojection_error_px": float(reconstruction.compute_mean_reprojection_error()),
        "mean_track_length": float(reconstruction.compute_mean_track_length()),
        "mean_observations_per_image": float(reconstruction.compute_mean_observations_per_reg_image()),
        "points": int(reconstruction.num_points3D()),
    }


def registered_names(reconstruction: Any) -> set[str]:
    return {reconstruction.image(image_id).name for image_id in reconstruction.reg_image_ids()}

