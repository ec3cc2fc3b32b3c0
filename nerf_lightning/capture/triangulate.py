"""Sparse points of a capture that has poses but no points (an instant-ngp ``transforms.json``, an LLFF
``poses_bounds.npy``): COLMAP's point triangulator run on the training views with their poses held fixed, through
``pycolmap`` (the ``colmap`` extra).

3DGS and gsplat start the Gaussians from the sparse points COLMAP's mapper left; captures published with poses
alone have lost them. The poses are known, so nothing is mapped: SIFT features of every training view (inside its
mask where the views have masks, so that the points lie on the object), matches verified by two-view geometry
between views that look at the same part of the scene (every pair of a small capture; each view with its nearest
others, by position and viewing direction, of a larger one), then each verified track triangulated from the fixed
cameras and kept where it reprojects within COLMAP's bounds. The points come out in the views' own world.

The views are triangulated as they are loaded (undistorted, downscaled): the points are where the Gaussians are
fitted to.
"""

from __future__ import annotations

import contextlib
import hashlib
import importlib.metadata
import inspect
import io
import json
import logging
import tempfile
import time
from pathlib import Path
from typing import Any

import numpy as np
import torch

from nerf_lightning.capture.colmap import (chunks, colmap_log, database_statistics, exhaustive_pairs, extract_features, import_pycolmap,
                                           match_features)
from nerf_lightning.capture.reconstruction import model_statistics, sparse_points
from nerf_lightning.capture.retrieval import nearest_pairs
from nerf_lightning.data.formats.shared import default_cache
from nerf_lightning.data.points import SparsePoints
from nerf_lightning.data.scene import Views
from nerf_lightning.io import write_atomic, write_png

log = logging.getLogger(__name__)

# a capture of at most this many views matches every pair; a larger one each view with its nearest NEIGHBOURS
ALL_PAIRS_UP_TO = 40
NEIGHBOURS = 20


def pose_pairs(c2w: torch.Tensor, neighbours: int = NEIGHBOURS, chunk: int = 100) -> list[list[tuple[int, int]]]:
    """(N, 4, 4) OpenCV camera-to-world -> pairs (i, j), i < j, of views likely to see the same points, in chunks of
    ``chunk``: each view with the ``neighbours`` others nearest by the distance of their centres (over the cameras'
    mean distance from their centroid) plus one minus the cosine between their viewing directions; views looking away
    from each other (more than 90 degrees) are never paired."""
    centres, forward = c2w[:, :3, 3].double(), c2w[:, :3, 2].double()
    spread = (centres - centres.mean(dim=0)).norm(dim=-1).mean().clamp_min(1e-12)
    cosine = forward @ forward.T
    distance = torch.cdist(centres, centres) / spread + (1.0 - cosine)
    distance[cosine <= 0.0] = torch.inf
    return [list(part) for part in chunks(sorted(nearest_pairs(-distance, neighbours)), chunk)]


def write_views(views: Views, folder: Path, masks: bool) -> list[str]:
    """Each view's image as ``folder/images/<index>.png`` and, with ``masks``, COLMAP's mask of it (255 on the
    object) as ``folder/masks/<index>.png.png`` -> the image names."""
    (folder / "images").mkdir(parents=True, exist_ok=True)
    if masks:
        (folder / "masks").mkdir(parents=True, exist_ok=True)
    names = []
    for index in range(len(views)):
        name = f"{index:05d}.png"
        write_png(folder / "images" / name, views.images[index])  # uint8 as it is, floats rounded
        if masks:
            write_png(folder / "masks" / f"{name}.png", views.masks[index].float())
        names.append(name)
    return names


def matched_names(database: Path) -> set[str]:
    """The names of the images in at least one geometrically verified pair of the ``database``: the triangulator's
    correspondence graph holds only those, and COLMAP fails (out of range, on a worker thread) on a posed image
    outside it."""
    pycolmap = import_pycolmap()
    with contextlib.closing(pycolmap.Database.open(database)) as opened:
        names = {image.image_id: image.name for image in opened.read_all_images()}
        pair_ids, inliers = opened.read_two_view_geometry_num_inliers()
        return {names[image_id] for pair_id, count in zip(pair_ids, inliers) if count > 0
                for image_id in pycolmap.pair_id_to_image_pair(pair_id)}


def posed_model(database: Path, views: Views, names: list[str], kept: set[str]) -> Any:
    """A ``pycolmap.Reconstruction`` of the known cameras and poses of the views named in ``kept`` (``names``: each
    view's image name), under the ids the database gave their images; the database's cameras are set to the views'
    pinhole intrinsics (the triangulator reads both)."""
    pycolmap = import_pycolmap()
    model = pycolmap.Reconstruction()
    with contextlib.closing(pycolmap.Database.open(database)) as opened:
        by_name = {image.name: image for image in opened.read_all_images()}
        for index, name in enumerate(names):
            if name not in kept:
                continue
            image = by_name[name]
            K = views.K[index].double()
            camera = pycolmap.Camera(model="PINHOLE", width=views.width, height=views.height, camera_id=image.camera_id,
                                     params=[float(K[0, 0]), float(K[1, 1]), float(K[0, 2]), float(K[1, 2])])
            opened.update_camera(camera)
            model.add_camera_with_trivial_rig(camera)
            w2c = torch.linalg.inv(views.c2w[index].double()).numpy()
            model.add_image_with_trivial_frame(pycolmap.Image(name=name, camera_id=image.camera_id, image_id=image.image_id),
                                               pycolmap.Rigid3d(pycolmap.Rotation3d(w2c[:3, :3]), w2c[:3, 3]))
    return model


def triangulate_views(views: Views, *, masks: bool = True, max_features: int = 8192, neighbours: int = NEIGHBOURS, seed: int = 0,
                      progress: bool = False, verbose: bool = False) -> tuple[SparsePoints, dict[str, Any]]:
    """Sparse points of the scene the posed ``views`` see (their images and poses; see the module's docstring) ->
    the points in the views' world with their colours, and what each stage took and left: ``seconds`` (features,
    matching, triangulation), ``matches`` (:func:`~nerf_lightning.capture.colmap.database_statistics`), the views
    in a verified pair (``views_matched``) and the model's statistics
    (:func:`~nerf_lightning.capture.reconstruction.model_statistics`).

    Args:
        masks: keep each view's features inside its mask, where the views have masks.
        max_features: SIFT features kept a view.
        neighbours: the views each view is matched with beyond :data:`ALL_PAIRS_UP_TO` views (:func:`pose_pairs`).
        seed: the seed of the matches' RANSAC and of the triangulator.
    A view in no verified pair (no features: an empty mask, a blank photo) is left out; where fewer than 2 views
    matched, no points come back.
    """
    if views.images is None:
        raise ValueError("triangulating sparse points needs the views' images")
    if len(views) < 2:
        raise ValueError(f"triangulating sparse points needs at least 2 posed views, got {len(views)}")
    pycolmap = import_pycolmap()
    masks = masks and views.masks is not None
    seconds = {}
    with tempfile.TemporaryDirectory(prefix="nerf-triangulate-") as scratch, colmap_log(verbose):
        folder = Path(scratch)
        database = folder / "database.db"
        started = time.perf_counter()
        names = write_views(views, folder, masks)
        extract_features(database, folder / "images", names, "PINHOLE", single_camera=False, max_size=max(views.height, views.width),
                         max_features=max_features, progress=progress, masks=folder / "masks" if masks else None)
        seconds["features"] = time.perf_counter() - started

        started = time.perf_counter()
        pairs = exhaustive_pairs(len(views)) if len(views) <= ALL_PAIRS_UP_TO else pose_pairs(views.c2w, neighbours)
        match_features(database, names, pairs, folder / "pairs", seed, progress)
        seconds["matching"] = time.perf_counter() - started
        matches = database_statistics(database)

        started = time.perf_counter()
        kept = matched_names(database)
        if len(kept) < 2:  # nothing to triangulate: no view matched another
            return SparsePoints.mapped(np.zeros((0, 3)), np.zeros((0, 3), dtype=np.uint8)), \
                {"seconds": {stage: round(value, 2) for stage, value in seconds.items()}, "matches": matches, "points": 0,
                 "views_matched": len(kept)}
        # the triangulator's own sampling seeded, not left to COLMAP's default, so that the same views give the same
        # points (tested, to a few points); COLMAP's global generator too, as map_images seeds it, which
        # triangulate_points does not seed from the options
        pycolmap.set_random_seed(seed)
        options = pycolmap.IncrementalPipelineOptions()
        options.random_seed = seed
        model = pycolmap.triangulate_points(posed_model(database, views, names, kept), database, folder / "images", folder / "sparse",
                                            options=options)
        seconds["triangulation"] = time.perf_counter() - started
        positions, colours = sparse_points(model)
        statistics = model_statistics(model)
    report = {"seconds": {stage: round(value, 2) for stage, value in seconds.items()}, "matches": matches, **statistics,
              "views_matched": len(kept)}
    return SparsePoints.mapped(positions, colours), report


# part of the cache's key: bump it when the same views and settings would give other points (a change in
# triangulate_views, or in capture/colmap.py's feature extraction or matching), so that the points cached before are
# made again
CACHE_VERSION = 1
# the settings of triangulate_views that say what is shown, not what comes back: left out of the key
NOT_IN_KEY = ("views", "progress", "verbose")
# the settings and their defaults, read once (not from whatever the module's name points at later)
TRIANGULATE_SIGNATURE = inspect.signature(triangulate_views)


def plain(value: Any) -> Any:
    """A numpy number as the Python number JSON writes (the report's statistics may hold them)."""
    if hasattr(value, "item"):
        return value.item()
    raise TypeError(f"{type(value).__name__} is not JSON serialisable")


def views_digest(views: Views, settings: dict[str, Any]) -> str:
    """A hex digest of what :func:`triangulate_views` reads of the ``views`` (images, masks where ``settings`` use
    them, K, c2w, size), of its ``settings`` as they take effect (its defaults filled in), and of pycolmap's version:
    the same digest, the same points."""
    bound = TRIANGULATE_SIGNATURE.bind_partial(views, **settings)
    bound.apply_defaults()
    effective = {key: value for key, value in bound.arguments.items() if key not in NOT_IN_KEY}
    try:
        version = importlib.metadata.version("pycolmap")
    except importlib.metadata.PackageNotFoundError:  # nothing is cached then: triangulate_views says pycolmap is missing
        version = None
    digest = hashlib.blake2b(digest_size=20)
    header = {"version": CACHE_VERSION, "pycolmap": version, "all_pairs_up_to": ALL_PAIRS_UP_TO, "height": views.height,
              "width": views.width, **effective}
    digest.update(json.dumps(header, sort_keys=True).encode())
    for tensor in (views.K, views.c2w, views.images, views.masks if effective["masks"] else None):
        if tensor is None:
            digest.update(b"none")
            continue
        digest.update(f"{tensor.dtype}{tuple(tensor.shape)}".encode())
        for view in tensor:  # a view at a time: a stack that is not one contiguous array is copied a view at a time
            digest.update(memoryview(np.ascontiguousarray(view.detach().cpu().numpy())).cast("B"))
    return digest.hexdigest()


def triangulate_views_once(views: Views, *, masks: bool = True, cache_dir: str | Path | None = None,
                           **settings: Any) -> tuple[SparsePoints, dict[str, Any]]:
    """:func:`triangulate_views`, its points kept in ``cache_dir/triangulated`` (None: ``NERF_LIGHTNING_CACHE``,
    default ~/.cache/nerf_lightning) under a digest of the views and settings (:func:`views_digest`), so that the
    runs after the first on the same training views (a sweep, a run started again) load them instead of matching
    again. The report of a loaded run is the first run's, with ``cached`` set to the file it came from. The cache
    never stops a run: a file that cannot be read is made again, one that cannot be written is not kept, each
    after one warning."""
    masks = masks and views.masks is not None
    folder = Path(cache_dir or default_cache()) / "triangulated"
    path = folder / f"{views_digest(views, {'masks': masks, **settings})}.npz"
    if path.is_file():
        try:
            with np.load(path) as stored:
                points = SparsePoints.mapped(stored["positions"], stored["colours"])
                report = json.loads(str(stored["report"]))
            return points, {**report, "cached": str(path)}
        except Exception as error:  # noqa: BLE001 - a damaged file (empty, cut short: EOFError, BadZipFile, ...) is made again
            log.warning("the cached sparse points %s could not be read (%s: %s); triangulating again", path, type(error).__name__, error)
    points, report = triangulate_views(views, masks=masks, **settings)
    stored = io.BytesIO()
    np.savez(stored, positions=points.positions.numpy(), colours=points.colours.numpy(), report=json.dumps(report, default=plain))
    try:
        write_atomic(path, stored.getvalue())  # whole or not at all, whichever process finishes last
    except OSError as error:  # a full disk, a read-only home: this run goes on, the next triangulates again
        log.warning("the sparse points could not be kept in %s (%s); the next run on these views triangulates them again", folder, error)
    return points, report
