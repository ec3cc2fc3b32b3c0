"""The checks that stop ``nerf-process-data`` on a model it cannot use, each with one line that names the images left
out and what to change: too few posed (:func:`check_registered`), a model the pose checks refuse
(:func:`apply_pose_checks`), poses the masks disagree with (:func:`check_silhouettes`).
"""

from __future__ import annotations

import logging
from collections.abc import Sequence
from pathlib import Path
from typing import Any

from nerf_lightning.capture.images import listed
from nerf_lightning.capture.model_checks import MIN_POINTS
from nerf_lightning.capture.posing import PosingPass
from nerf_lightning.capture.settings import CaptureSettings

log = logging.getLogger(__name__)

ADVICE = ("photos with more overlap (each part of the scene in 3 or more of them, taken a step apart, not turning on "
          "the spot), sharper ones (more light, steadier hands), a textured subject")


def check_registered(registered: int, unregistered: list[str], given: int, source: Path, matcher: str, min_registered: float,
                     escalated: bool = False, left_out: Sequence[str] = ()) -> None:
    """ValueError, one line naming the images left out and what to change, when COLMAP posed fewer than 3 images or
    fewer than ``min_registered`` of them (``escalated``: also with the stronger settings, which the line says;
    ``left_out``: photos it registered on too few points to hold them, named apart)."""
    change = ("try matcher=exhaustive, " if matcher == "sequential" else "") + ADVICE
    counted = "registered" if not left_out else f"posed (registered, less {len(left_out)} seeing fewer than {MIN_POINTS} of its points)"
    missing = "these did not register" if not left_out else "these are not posed"
    if escalated:
        change = "stronger settings (features at twice the size, affine shapes, guided matching) did not help either; " + change
    if registered == 0 and not left_out:
        raise ValueError(f"COLMAP registered none of the {given} images of {source}: no two of them matched well enough "
                         f"to start a model; {change}")
    unregistered = [*unregistered, *left_out]
    if registered < 3:
        raise ValueError(f"COLMAP {counted} only {registered} of the {given} images of {source}, 3 are needed; "
                         f"{missing}: {listed(unregistered)}; {change}")
    if registered < min_registered * given:
        raise ValueError(f"COLMAP {counted} {registered} of the {given} images of {source} ({100.0 * registered / given:.0f}%, "
                         f"under min_registered={min_registered:g}); {missing}: {listed(unregistered)}; "
                         f"{change}; or min_registered=0 to keep the {registered} that did")


def check_silhouettes(agreement: dict[str, Any], registered: int, source: Path, min_mask_agreement: float) -> None:
    """ValueError, one line, where the median registered photo's mask agrees with the poses less than
    ``min_mask_agreement`` (:func:`~nerf_lightning.capture.silhouettes.silhouette_agreement`): COLMAP's model is
    wrong, however many photos it registered."""
    median = agreement["median_coverage"]
    if median < min_mask_agreement:
        raise ValueError(f"COLMAP registered {registered} images of {source}, but the poses do not agree with the masks: in the "
                         f"median photo only {100.0 * median:.0f}% of the mask's rays meet the object all the masks carve "
                         f"(under min_mask_agreement={min_mask_agreement:g}), so the cameras are in the wrong places; "
                         "the photos are likely too far apart: take one every 5 to 10 degrees round the object, with each "
                         "photo overlapping its neighbours by two thirds (docs/guides/real-captures.md); or min_mask_agreement=0 "
                         "to keep this model")


def apply_pose_checks(kept: PosingPass, names: Sequence[str], source: Path, matcher: str, settings: CaptureSettings, escalated: bool,
                      report: dict[str, Any]) -> tuple[list[str], list[str]]:
    """What the pose checks found of the ``kept`` pass acted on: kept as ``report["pose_checks"]``, their warnings
    logged, and (with ``check_poses``) ValueError where they refuse the model; then :func:`check_registered` of what
    is posed (``escalated``: with the stronger settings too). Returns the photos left out, registered on too few
    points, and of ``names`` those not registered."""
    checks, posed, left_out = kept.checks, kept.posed, []
    if checks is not None:  # (no model: the registration check below says so)
        report["pose_checks"] = checks
        if settings.check_poses and checks["refuse"]:
            raise ValueError(f"COLMAP registered {len(posed)} images of {source}, but its model is wrong: "
                             + "; ".join(checks["refuse"]) + "; or check_poses=false to keep this model")
        for said in checks["warn"] + ([] if settings.check_poses else checks["refuse"]):
            log.warning("%s", said)
        left_out = sorted(set(checks["thinly_posed"]) - posed)
    unregistered = [name for name in names if name not in posed and name not in left_out]
    check_registered(len(posed), unregistered, len(names), source, matcher, settings.min_registered, escalated=escalated,
                     left_out=left_out)
    return left_out, unregistered
