"""The last stage of COLMAP's structure from motion, mapping a matched database (:mod:`~nerf_lightning.capture.colmap`)
into camera poses and points, run in-process through ``pycolmap``; the whole of it (:func:`reconstruct`); and the
result as a nerfstudio ``transforms.json``.

Mapping runs both COLMAP mappers by default, the global one (GLOMAP) and the incremental one, and keeps the model that
explains the most geometrically verified matches. A model can reproject its own points to a pixel and still be
wrong: on fox's 50 photos (two arcs of a walk round a mounted fox before a repeating rose wallpaper, the photos between
them missing) either mapper, depending on the matches' RANSAC seed, joins the second arc to the first through
wallpaper matches one repeat off, every image registered and the arcs misplaced; such a model contradicts the
fox's own matches between the arcs, which the right one explains (docs/benchmarks.md, "Both COLMAP mappers").

Written against pycolmap 4.2 (``Image.cam_from_world()``, ``global_mapping``).
"""

from __future__ import annotations

import contextlib
import shutil
import time
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np
import torch
from tqdm import tqdm

from nerf_lightning.capture.choices import CAMERA_MODELS, CAMERA_PARAMETERS, COLMAP_EXTRA, MAPPERS
from nerf_lightning.capture.colmap import (colmap_log, database_statistics, exhaustive_pairs, extract_features, import_pycolmap,
                                           loop_closure_pairs, match_features, overlapping_pairs, sequential_pairs, verified_pairs)
from nerf_lightning.capture.images import mask_name, natural_key
from nerf_lightning.geometry.cameras import opengl_to_opencv


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
        matcher: ``exhaustive`` or ``sequential`` (see :func:`~nerf_lightning.capture.colmap.choose_matcher`), or ``overlapping``
            (:func:`~nerf_lightning.capture.colmap.overlapping_pairs`, with the pairs ``verified_in`` a first pass's database: the stronger pass's).
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
        :func:`~nerf_lightning.capture.colmap.database_statistics`), and the cameras whose EXIF focal length was corrected (``focal_priors``,
        :func:`~nerf_lightning.capture.colmap.correct_focal_priors`), and the other mapper's model (``other_model``; None where only one built a
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
    """A COLMAP camera as transforms.json keys: ``camera_model``, ``fl_x``, ``fl_y``, ``cx``, ``cy``, its lens's
    coefficients (``k1``, ``k2``, ``p1``, ``p2``, zero where the model has no such term; ``k1`` to ``k4`` for
    ``OPENCV_FISHEYE``, as nerfstudio writes them), ``w``, ``h``, in the pixels of the images it saw."""
    model = camera.model.name
    if model not in CAMERA_PARAMETERS:
        raise ValueError(f"COLMAP camera model {model} is not one the transforms.json loader reads ({', '.join(CAMERA_MODELS)})")
    values = dict(zip(CAMERA_PARAMETERS[model], (float(value) for value in camera.params)))
    if "f" in values:
        values["fl_x"] = values["fl_y"] = values.pop("f")
    keys = {"camera_model": model, "fl_x": values["fl_x"], "fl_y": values["fl_y"], "cx": values["cx"], "cy": values["cy"]}
    coefficients = ("k1", "k2", "k3", "k4") if model == "OPENCV_FISHEYE" else ("k1", "k2", "p1", "p2")
    keys.update({key: values.get(key, 0.0) for key in coefficients})
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
