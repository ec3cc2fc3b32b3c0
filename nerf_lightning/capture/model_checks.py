"""Does a COLMAP model put the photos in the right places? Checks that need no reference poses and no masks.

A model can reproject its own points to a third of a pixel and explain 96 % of its verified matches and still be
wrong: photos too far apart share few matches, some of them false (a shiny or symmetric object seen from opposite
sides), and the mapper strings the photos into a ring that is not the capture's (docs/guides/real-captures.md,
"When posing is wrong"). What such a model shows, measured on cases made from the shared captures:

- **the two mappers disagree.** ``mapper=auto`` builds a model with each of COLMAP's mappers, the global one (all
  rotations at once) and the incremental one (a photo at a time). On a capture they can both pose, right models agree
  to a degree or two; a model strung through false matches is strung differently by each, or one of them gives up
  (:func:`mappers_agreement`);
- **the photos hang by a thread.** Each photo of a right model is tied by verified matches to several others; in a
  wrong one most photos have one or two, through pairs with few inliers (:func:`view_graph`).

:func:`pose_flags` turns them into flags, at thresholds calibrated on right and wrong models of fox's and the cape's
photos (subsets, sparser and sparser, a shuffled order, a repeated photo): the report's ``pose_checks``.
A repeated photo (the same picture twice, or two taken without moving) is named too (:func:`repeated_photos`): it is
harmless to the poses, but it teaches a model nothing and weighs its view twice.
"""

from __future__ import annotations

import contextlib
from pathlib import Path
from typing import Any

import numpy as np
import torch

from nerf_lightning.capture.colmap import camera_from_world, import_pycolmap
from nerf_lightning.geometry.alignment import camera_pose_errors

# a pair holds two photos together when it has at least this many verified inlier matches (COLMAP's own floor is 15)
STRONG_PAIR = 30
# the mappers agree when, after the similarity that best aligns their common cameras, the median camera is within
# these of the other mapper's
AGREE_DEGREES = 5.0
AGREE_PERCENT = 5.0
# a model whose median photo is tied to fewer other photos than this, by strong pairs, hangs by a thread
MIN_NEIGHBOURS = 2
# two photos are one picture twice when their matches move less than this (pixels, median) and cover this share of
# the fewer keypoints
REPEATED_PX = 1.0
REPEATED_SHARE = 0.5


def cameras_of(reconstruction: Any) -> dict[str, torch.Tensor]:
    """Registered image name -> (4, 4) camera-to-world (OpenCV axes), float64."""
    return {reconstruction.image(image_id).name: torch.from_numpy(np.linalg.inv(camera_from_world(reconstruction.image(image_id))))
            for image_id in reconstruction.reg_image_ids()}


def mappers_agreement(first: Any, second: Any) -> dict[str, Any] | None:
    """Two models of one capture compared on the photos both registered, after the similarity that best aligns the
    first's cameras to the second's (:func:`~nerf_lightning.geometry.alignment.camera_pose_errors`): how many, the
    median and largest rotation (degrees) and centre (percent of the second's spread) differences. None under 3
    common photos (nothing to align)."""
    ours, theirs = cameras_of(first), cameras_of(second)
    common = sorted(set(ours) & set(theirs))
    if len(common) < 3:
        return None
    errors = camera_pose_errors(torch.stack([ours[name] for name in common]), torch.stack([theirs[name] for name in common]))
    spread = max(float(errors["spread"]), 1e-12)
    return {"compared": len(common),
            "median_rotation_deg": round(float(errors["rotation_error"].median()), 3),
            "max_rotation_deg": round(float(errors["rotation_error"].max()), 3),
            "median_position_percent_of_spread": round(100.0 * float(errors["position_error"].median()) / spread, 3),
            "max_position_percent_of_spread": round(100.0 * float(errors["position_error"].max()) / spread, 3)}


def view_graph(database: Path, reconstruction: Any) -> dict[str, Any]:
    """How the registered photos are tied together by verified matches in ``database``: each photo's strong pairs
    (at least :data:`STRONG_PAIR` inliers) with other registered photos, the median and fewest a photo, the photos
    with none, and the median inliers of a verified pair between registered photos."""
    pycolmap = import_pycolmap()
    registered = {image_id: reconstruction.image(image_id).name for image_id in reconstruction.reg_image_ids()}
    neighbours = {image_id: 0 for image_id in registered}
    inliers_of_pairs = []
    with contextlib.closing(pycolmap.Database.open(database)) as opened:
        pair_ids, inliers = opened.read_two_view_geometry_num_inliers()
    for pair_id, count in zip(pair_ids, inliers):
        first, second = pycolmap.pair_id_to_image_pair(pair_id)
        if count <= 0 or first not in registered or second not in registered:
            continue
        inliers_of_pairs.append(int(count))
        if count >= STRONG_PAIR:
            neighbours[first] += 1
            neighbours[second] += 1
    counts = list(neighbours.values())
    return {"median_neighbours": float(np.median(counts)) if counts else 0.0, "fewest_neighbours": int(min(counts, default=0)),
            "unconnected": sorted(registered[image_id] for image_id, count in neighbours.items() if count == 0),
            "verified_pairs": len(inliers_of_pairs),
            "median_inliers_per_pair": float(np.median(inliers_of_pairs)) if inliers_of_pairs else 0.0}


def repeated_photos(database: Path, reconstruction: Any) -> list[list[str]]:
    """Pairs of registered photos that are one picture twice: their verified matches cover most keypoints
    (:data:`REPEATED_SHARE` of the fewer) and move less than :data:`REPEATED_PX` (median)."""
    pycolmap = import_pycolmap()
    registered = set(reconstruction.reg_image_ids())
    repeated = []
    with contextlib.closing(pycolmap.Database.open(database)) as opened:
        pair_ids, geometries = opened.read_two_view_geometries()
        for pair_id, geometry in zip(pair_ids, geometries):
            first, second = pycolmap.pair_id_to_image_pair(pair_id)
            matches = geometry.inlier_matches
            if first not in registered or second not in registered or len(matches) == 0:
                continue
            fewer = min(opened.num_keypoints_for_image(first), opened.num_keypoints_for_image(second))
            if len(matches) < REPEATED_SHARE * fewer:
                continue
            moved = opened.read_keypoints(first)[matches[:, 0], :2] - opened.read_keypoints(second)[matches[:, 1], :2]
            if float(np.median(np.linalg.norm(moved, axis=1))) < REPEATED_PX:
                repeated.append(sorted([reconstruction.image(first).name, reconstruction.image(second).name]))
    return sorted(repeated)


def pose_flags(checks: dict[str, Any], registered: int) -> list[str]:
    """What :func:`pose_checks` found that says the model is likely wrong, a sentence each (empty: nothing)."""
    flags = []
    agreement = checks.get("mappers")
    if agreement is not None and (agreement["median_rotation_deg"] > AGREE_DEGREES or agreement["median_position_percent_of_spread"] > AGREE_PERCENT):
        flags.append(f"COLMAP's two mappers place the {agreement['compared']} photos both posed differently (the median photo "
                     f"{agreement['median_rotation_deg']:.1f} degrees and {agreement['median_position_percent_of_spread']:.0f}% of the "
                     "cameras' spread apart), so at least one of them strung the photos wrongly")
    graph = checks["view_graph"]
    if registered >= 3 and graph["median_neighbours"] < MIN_NEIGHBOURS:
        flags.append(f"the median photo shares {STRONG_PAIR} or more verified matches with {graph['median_neighbours']:g} other posed "
                     f"photos (a right model's share with {MIN_NEIGHBOURS} or more), so the poses hang on few matches")
    return flags


def pose_checks(database: Path, kept: Any, other: Any | None) -> dict[str, Any]:
    """The checks of the kept model (``other``: the other mapper's model, or None): ``mappers``
    (:func:`mappers_agreement`), ``view_graph``, ``repeated`` (:func:`repeated_photos`) and ``flags``
    (:func:`pose_flags`)."""
    checks: dict[str, Any] = {"mappers": mappers_agreement(kept, other) if other is not None else None,
                              "view_graph": view_graph(database, kept), "repeated": repeated_photos(database, kept)}
    checks["flags"] = pose_flags(checks, kept.num_reg_images())
    return checks
