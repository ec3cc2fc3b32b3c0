"""Does a COLMAP model put the photos in the right places? Checks that need no reference poses and no masks.

A model can reproject its own points to a third of a pixel and explain 95 % of its verified matches and still be
wrong: photos too far apart share few matches (20 of moldGoldCape's photos, 18 degrees apart, give 20 verified pairs
among 15 posed photos), and COLMAP's global mapper places a photo from its pairs' relative poses alone, which for a
pair of few matches can be any of several. Calibrated on right and wrong models made from the shared captures
(subsets of fox's and the cape's photos, with and without masks, a shuffled order, a repeated photo, the procedural
turntable without masks: docs/guides/real-captures.md, "Posing that knows when it is wrong"), what parts them is:

- **photos posed on almost no points** (:func:`thinly_posed`): in the wrong models most photos see 0 to 5 of the
  model's 3D points; in the right ones every photo but a stray one sees 6 or more. Such a photo is left out and named
  (``nerf-process-data`` then applies its ``min_registered`` floor to the photos left);
- **cameras spread far wider than they see** (:func:`camera_spread`): 11 to 49 times the distance at which they see
  the points in the wrong models, 0.1 to 1.05 in the right ones. Refused;
- **one picture twice** (:func:`repeated_photos`): two photos whose matches do not move. One is harmless and named;
  most photos static against one another is a turntable photographed without masks, where the room stands still and
  the model is of the room, not the object. Refused.

Also recorded, as evidence rather than verdicts: how the photos are tied together (:func:`view_graph`) and whether
COLMAP's two mappers agree (:func:`mappers_agreement`; on right fox subsets they disagree too, where the model kept,
the one that explains more verified matches, is the right one).
"""

from __future__ import annotations

import contextlib
import math
from pathlib import Path
from typing import Any

import numpy as np
import torch

from nerf_lightning.capture.colmap import import_pycolmap, verified_pairs
from nerf_lightning.capture.reconstruction import camera_from_world

# a pair holds two photos together when it has at least this many verified inlier matches (COLMAP's own floor is 15)
STRONG_PAIR = 30
# a photo seeing fewer of the model's 3D points than this is not held in place by them: six is the fewest that fix a
# camera's pose by the direct linear transform. In the wrong models of the calibration most photos see 0 to 5; in
# the right ones a few photos see 6 to 30, posed within a degree or two, which a higher floor would throw away
MIN_POINTS = 6
# cameras spread wider than this many times the median distance at which they see the model's points: in the wrong
# models 11 to 49, in the right ones 0.1 (forward-facing) to 1.05 (all round an object)
MAX_SPREAD = 4.0
# two photos are one picture twice when their matches move less than this (pixels, median) and cover this share of
# the fewer keypoints
REPEATED_PX = 1.0
REPEATED_SHARE = 0.5
# a model whose photos are this share or more in repeated pairs is of a scene that did not move against the camera
MOSTLY_REPEATED = 0.25


def cameras_of(reconstruction: Any) -> dict[str, torch.Tensor]:
    """Registered image name -> (4, 4) camera-to-world (OpenCV axes), float64."""
    return {reconstruction.image(image_id).name: torch.from_numpy(np.linalg.inv(camera_from_world(reconstruction.image(image_id))))
            for image_id in reconstruction.reg_image_ids()}


def mappers_agreement(first: Any, second: Any) -> dict[str, Any] | None:
    """Two models of one capture compared on the photos both registered, without aligning them (an alignment fitted
    to the centres turns freely about the line a short arc of cameras lies on): over every pair of common photos, the
    angle between the two models' rotations from one photo to the other, and between their directions from one
    photo's centre to the other's, seen from the first photo. The count and the medians in degrees; None under 3
    common photos."""
    ours, theirs = cameras_of(first), cameras_of(second)
    common = sorted(set(ours) & set(theirs))
    if len(common) < 3:
        return None
    a, b = torch.stack([ours[name] for name in common]), torch.stack([theirs[name] for name in common])
    i, j = torch.triu_indices(len(common), len(common), offset=1)

    def relative(c2w: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        rotation = c2w[i, :3, :3].transpose(-1, -2) @ c2w[j, :3, :3]  # (P, 3, 3) photo j's axes in photo i's
        direction = (c2w[i, :3, :3].transpose(-1, -2) @ (c2w[j, :3, 3] - c2w[i, :3, 3])[..., None])[..., 0]
        return rotation, torch.nn.functional.normalize(direction, dim=-1)

    (rotation_a, direction_a), (rotation_b, direction_b) = relative(a), relative(b)
    cos_rotation = (((rotation_a.transpose(-1, -2) @ rotation_b).diagonal(dim1=-2, dim2=-1).sum(-1) - 1.0) / 2.0).clamp(-1.0, 1.0)
    cos_direction = (direction_a * direction_b).sum(-1).clamp(-1.0, 1.0)
    return {"compared": len(common), "median_rotation_deg": round(float(torch.rad2deg(cos_rotation.acos()).median()), 3),
            "median_direction_deg": round(float(torch.rad2deg(cos_direction.acos()).median()), 3)}


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
        for first, second, geometry in verified_pairs(opened, registered):
            matches = geometry.inlier_matches
            fewer = min(opened.num_keypoints_for_image(first), opened.num_keypoints_for_image(second))
            if len(matches) < REPEATED_SHARE * fewer:
                continue
            moved = opened.read_keypoints(first)[matches[:, 0], :2] - opened.read_keypoints(second)[matches[:, 1], :2]
            if float(np.median(np.linalg.norm(moved, axis=1))) < REPEATED_PX:
                repeated.append(sorted([reconstruction.image(first).name, reconstruction.image(second).name]))
    return sorted(repeated)


def points_seen(reconstruction: Any) -> dict[str, int]:
    """Each registered photo, by name, -> how many of the model's 3D points it sees."""
    return dict(sorted((reconstruction.image(image_id).name, int(reconstruction.image(image_id).num_points3D))
                       for image_id in reconstruction.reg_image_ids()))


def thinly_posed(seen: dict[str, int]) -> list[str]:
    """The photos of :func:`points_seen` that see fewer than :data:`MIN_POINTS` of the model's 3D points."""
    return sorted(name for name, count in seen.items() if count < MIN_POINTS)


def camera_spread(reconstruction: Any) -> float:
    """How far the posed cameras are spread against how far they see: the root mean square distance of their centres
    from their mean over the median distance from a camera to the points it sees. Around 1 for photos walked round
    an object, a few tenths for a forward-facing capture, near 0 where the model says the camera did not move."""
    centres, distances = [], []
    for image_id in reconstruction.reg_image_ids():
        image = reconstruction.image(image_id)
        centre = np.linalg.inv(camera_from_world(image))[:3, 3]
        centres.append(centre)
        seen = [reconstruction.points3D[point.point3D_id].xyz for point in image.points2D if point.has_point3D()]
        if seen:
            distances.append(float(np.median(np.linalg.norm(np.asarray(seen) - centre, axis=1))))
    if len(centres) < 2 or not distances:
        return float("nan")
    centres = np.asarray(centres)
    return float(np.sqrt(((centres - centres.mean(0)) ** 2).sum(1).mean()) / max(np.median(distances), 1e-12))


def pose_flags(checks: dict[str, Any], registered: int) -> dict[str, list[str]]:
    """What :func:`pose_checks` found, as sentences: ``refuse`` (the model is wrong; each says what was found, then
    after a semicolon why it matters and what to do) and ``warn`` (photos left out, a photo twice)."""
    refuse, warn = [], []
    thin = checks["thinly_posed"]
    if thin:
        warn.append(f"{len(thin)} of the {registered} posed photos see fewer than {MIN_POINTS} of the model's points, so nothing holds "
                    f"them in place (left out unless check_poses=false): {', '.join(thin[:6])}{', ...' if len(thin) > 6 else ''}")
    spread = checks.get("camera_spread")
    if spread is not None and spread > MAX_SPREAD:
        refuse.append(f"the posed cameras lie {spread:.0f} times farther apart than they are from what they see; a right model's "
                      f"cameras, walked round an object, about 1 (under {MAX_SPREAD:g} is taken as right), so the photos are strung "
                      "together in the wrong places: the photos are likely too far apart; take one every 5 to 10 degrees round the "
                      "object, each overlapping its neighbours by two thirds")
    repeated = checks["repeated"]
    in_repeats = {name for pair in repeated for name in pair}
    if registered and len(in_repeats) >= max(3, MOSTLY_REPEATED * registered):  # more than one pair: one is a repeat
        refuse.append(f"{len(in_repeats)} of the {registered} posed photos match another one without moving; the camera did not move "
                      "against what it matched (a turntable photographed without masks, whose room stands still), so the model "
                      "is of the room, not the object: give the masks (masks=)")
    elif repeated:
        warn.append("one picture twice (their matches do not move): " + "; ".join(" and ".join(pair) for pair in repeated))
    return {"refuse": refuse, "warn": warn}


def pose_checks(database: Path, kept: Any, other: Any | None) -> dict[str, Any]:
    """The checks of the kept model (``other``: the other mapper's model, or None): ``points_seen`` and
    ``thinly_posed``, ``repeated``, ``camera_spread`` (None where no photo sees a point), ``view_graph``, ``mappers``
    (:func:`mappers_agreement`; None with one model) and what they make of it (``refuse`` and ``warn``,
    :func:`pose_flags`)."""
    spread, seen = camera_spread(kept), points_seen(kept)
    checks: dict[str, Any] = {"thinly_posed": thinly_posed(seen), "points_seen": seen, "repeated": repeated_photos(database, kept),
                              "camera_spread": round(spread, 4) if math.isfinite(spread) else None,
                              "view_graph": view_graph(database, kept),
                              "mappers": mappers_agreement(kept, other) if other is not None else None}
    checks.update(pose_flags(checks, kept.num_reg_images()))
    return checks
