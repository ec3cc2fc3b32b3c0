"""The posing passes: the staged images posed by COLMAP (:func:`~nerf_lightning.capture.reconstruction.reconstruct`),
what the pose checks and, with masks, the masks' agreement find of the model, and the escalation: a capture posed too
few or wrong is posed again with stronger settings, and the better of the two models kept.
"""

from __future__ import annotations

import logging
import shutil
import time
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from nerf_lightning.capture.model_checks import pose_checks
from nerf_lightning.capture.reconstruction import reconstruct, reconstruction_to_transforms, registered_names, sparse_points
from nerf_lightning.capture.settings import CaptureSettings
from nerf_lightning.capture.silhouettes import silhouette_agreement

log = logging.getLogger(__name__)

# under this fraction registered, the capture is posed again with stronger settings (:func:`escalated_settings`)
ESCALATE_BELOW = 0.9
# with masks, also where the median photo's mask agrees with the model's poses less than this: right models of real
# captures agree about 0.9 or more, rough masks included, and a model wrong in part less (moldGoldCape's photos
# darkened to a quarter: all registered, 0.79, cameras degrees off; with the stronger settings 0.95 and right)
ESCALATE_AGREEMENT = 0.85


def escalated_settings(max_size: int, max_features: int, sizes: dict[str, tuple[int, int]]) -> dict[str, Any]:
    """The stronger settings a capture that registered too few is posed again with: features read at twice
    ``max_size`` (up to the photos' own size: a small object then covers more pixels), as many of them, SIFT with
    affine shapes and domain-size pooling, and guided matching. Not twice as many features: guided matching's cost
    grows with the square of their count, and on moldGoldCape's 1824 px photos 16 384 took 2.9 s a pair where 8 192
    took 0.4 s and kept two thirds of the inliers (docs/history/issue74-photos.md)."""
    longest = max(max(size) for size in sizes.values())
    return {"max_size": int(min(2 * max_size, max(longest, max_size))), "max_features": int(max_features), "strong": True}


def model_agreement(model: Any, posed: set[str], staging: Path, downscales: Sequence[int], seed: int) -> dict[str, Any] | None:
    """The staged masks' agreement with ``model``'s poses (:func:`~nerf_lightning.capture.silhouettes.silhouette_agreement`),
    or None where it posed fewer than 3 images (too few to carve a hull; the registration check stops those)."""
    if model is None or len(posed) < 3:
        return None
    transforms = reconstruction_to_transforms(model, mask_folder="masks")
    positions, _ = sparse_points(model)
    return silhouette_agreement(transforms, positions, staging, list(downscales), seed)


def agreement_of(agreement: dict[str, Any] | None) -> float | None:
    """The median photo's coverage of a masks' ``agreement`` (:func:`model_agreement`); None without one."""
    return None if agreement is None else agreement["median_coverage"]


def model_score(posed: set[str], agreement: dict[str, Any] | None, masks: bool) -> tuple[float, int]:
    """Which of two models of a capture to keep, the higher: the one with more photos posed, each weighted, where the
    capture has masks, by the masks' agreement with the poses (the median photo's), so that fewer photos posed right
    beat more posed partly wrong; on a tie, more photos posed. Under 3 posed, a model nothing can use: -1."""
    if len(posed) < 3:
        return (-1.0, len(posed))
    return (len(posed) * (agreement["median_coverage"] if masks and agreement is not None else 1.0), len(posed))


# the stronger pass matches every pair up to this many pairs (a capture of 25 photos), the pairs that can overlap beyond
STRONG_EVERY_PAIR_UP_TO = 300


def stronger_matcher(count: int) -> str:
    """The stronger pass's matching for ``count`` photos: every pair where they are few (a photo the first pass could
    not register has no verified pair to follow), else the pairs that can overlap
    (:func:`~nerf_lightning.capture.colmap.overlapping_pairs`), whose count grows with the photos, not their square."""
    return "exhaustive" if count * (count - 1) // 2 <= STRONG_EVERY_PAIR_UP_TO else "overlapping"


def matches_said(matches: dict[str, float]) -> str:
    """What features and matching left (:func:`~nerf_lightning.capture.colmap.database_statistics`), said in words:
    where a capture that registers few is lost."""
    return (f"{matches['keypoints_mean']:.0f} features a photo on average, {matches['keypoints_min']} in the fewest; "
            f"{matches['pairs_verified']} of {matches['pairs_matched']} pairs matched verified a geometry, "
            f"{matches['inliers_per_verified_pair']:.0f} matches a verified pair")


@dataclass
class PosingPass:
    """One posing of the staged images and what was found of it.

    Attributes:
        model: the ``pycolmap.Reconstruction`` COLMAP kept; None where its mapper built none.
        seconds: what each of COLMAP's stages took (features, matching, mapping).
        mapping: what :func:`~nerf_lightning.capture.reconstruction.reconstruct` says of its mapping (``mapper``,
            ``mappers``, ``matches``, ``focal_priors``, ``other_model``).
        checks: the pose checks' findings (:func:`~nerf_lightning.capture.model_checks.pose_checks`); None without a model.
        posed: the names of the photos it poses that the checks hold in place (all it registered with ``check_poses=false``).
        agreement: with masks, theirs with the poses (:func:`model_agreement`); None without masks or under 3 posed.
        refused: the checks refuse the model and ``check_poses`` acts on them.
    """

    model: Any
    seconds: dict[str, float]
    mapping: dict[str, Any]
    checks: dict[str, Any] | None
    posed: set[str]
    agreement: dict[str, Any] | None
    refused: bool


def pose_pass(staging: Path, colmap_dir: Path, names: Sequence[str], masked: bool, settings: CaptureSettings, seconds: dict[str, float],
              **options: Any) -> PosingPass:
    """``staging/images/<name>`` for each of ``names`` posed by COLMAP into ``colmap_dir``
    (:func:`~nerf_lightning.capture.reconstruction.reconstruct`, given ``options`` besides the ``settings``' mapper,
    camera, seed, progress and log, and ``staging/colmap/masks`` where ``masked``), checked; the seconds the masks'
    check takes added to ``seconds["silhouettes"]``."""
    model, stage_seconds, mapping = reconstruct(
        staging / "images", names, colmap_dir, mapper=settings.mapper, camera_model=settings.camera_model, single_camera=settings.single_camera,
        seed=settings.seed, masks=staging / "colmap" / "masks" if masked else None, progress=settings.progress, verbose=settings.verbose,
        **options)
    checks, posed = None, set()
    if model is not None:
        checks = pose_checks(colmap_dir / "database.db", model, mapping["other_model"])
        posed = registered_names(model) - (set(checks["thinly_posed"]) if settings.check_poses else set())
    agreement = None
    if masked:
        check_started = time.perf_counter()
        agreement = model_agreement(model, posed, staging, settings.downscales, settings.seed)
        seconds["silhouettes"] = seconds.get("silhouettes", 0.0) + time.perf_counter() - check_started
    return PosingPass(model, stage_seconds, mapping, checks, posed, agreement, refused=bool(settings.check_poses and checks and checks["refuse"]))


def escalation_reason(first: PosingPass, count: int, settings: CaptureSettings) -> str | None:
    """Why the first pass is posed again: ``model`` (the pose checks refuse it), ``registered`` (it posed under
    :data:`ESCALATE_BELOW` of the ``count`` images) or ``masks`` (the masks agree with its poses less than
    :data:`ESCALATE_AGREEMENT`, or than ``min_mask_agreement`` where that is set higher, so that a model that would
    stop on it is tried again too); None where it stands."""
    if first.refused:
        return "model"
    if len(first.posed) < ESCALATE_BELOW * count:
        return "registered"
    if first.agreement is not None and first.agreement["median_coverage"] < max(ESCALATE_AGREEMENT, settings.min_mask_agreement):
        return "masks"
    return None


def pose_capture(staging: Path, names: Sequence[str], sizes: dict[str, tuple[int, int]], matcher: str, masked: bool,
                 settings: CaptureSettings, seconds: dict[str, float], report: dict[str, Any]) -> PosingPass:
    """The staged images (``names``, of (width, height) ``sizes``) posed into ``staging/colmap`` with ``matcher``
    (:func:`pose_pass`), and where that falls short and ``settings.escalate``, again with stronger settings
    (:func:`pose_again`, which says so in ``report["escalated"]``); the pass kept. COLMAP's copies of the masks are
    removed, and the first pass's seconds of each stage added to ``seconds``."""
    first = pose_pass(staging, staging / "colmap", names, masked, settings, seconds, matcher=matcher, max_size=int(settings.max_size),
                      max_features=int(settings.max_features))
    why = escalation_reason(first, len(names), settings)
    kept = pose_again(staging, names, sizes, first, why, masked, settings, seconds, report) if settings.escalate and why else first
    shutil.rmtree(staging / "colmap" / "masks", ignore_errors=True)  # masks/ holds them, by the photos' names
    seconds.update(first.seconds)
    return kept


def pose_again(staging: Path, names: Sequence[str], sizes: dict[str, tuple[int, int]], first: PosingPass, why: str, masked: bool,
               settings: CaptureSettings, seconds: dict[str, float], report: dict[str, Any]) -> PosingPass:
    """The images posed again into ``staging/colmap_escalated`` with stronger settings (:func:`escalated_settings`,
    :func:`stronger_matcher`), ``why`` (:func:`escalation_reason`) said in a warning; the better of that pass and
    ``first`` (:func:`model_score`; one the checks refuse never kept over one they do not), its folder left as
    ``staging/colmap``. ``report["escalated"]`` says why, what each pass registered and matched, and which was kept;
    ``seconds["escalation"]`` what the second pass took."""
    stronger = escalated_settings(int(settings.max_size), int(settings.max_features), sizes)
    again_matcher = stronger_matcher(len(names))
    said = (f"COLMAP's model is wrong: {first.checks['refuse'][0].split(';')[0]}" if why == "model" else
            f"COLMAP posed {len(first.posed)} of the {len(names)} images" if why == "registered" else
            f"the masks agree with the poses in {100.0 * first.agreement['median_coverage']:.0f}% of the median photo's rays")
    log.warning("%s (%s); posing them again with stronger settings: features at %d px, %d of them, affine shapes and "
                "domain-size pooling, guided matching, %s (slower)", said, matches_said(first.mapping["matches"]),
                stronger["max_size"], stronger["max_features"],
                "on every pair" if again_matcher == "exhaustive" else
                "on the pairs that can overlap (neighbours in name order, the photos most alike, the pairs verified already)")
    again = pose_pass(staging, staging / "colmap_escalated", names, masked, settings, seconds, matcher=again_matcher,
                      verified_in=staging / "colmap" / "database.db", **stronger)
    report["escalated"] = {"why": why, "registered_before": len(first.posed), "matches_before": first.mapping["matches"],
                           "matches_after": again.mapping["matches"], "registered_after": len(again.posed), "matcher": again_matcher,
                           "settings": {key: value for key, value in stronger.items() if key != "strong"},
                           "seconds": round(sum(again.seconds.values()), 2)}
    if masked:
        report["escalated"].update({"mask_agreement_before": agreement_of(first.agreement),
                                    "mask_agreement_after": agreement_of(again.agreement)})
    seconds["escalation"] = sum(again.seconds.values())
    better = (not again.refused, model_score(again.posed, again.agreement, masked)) > \
             (not first.refused, model_score(first.posed, first.agreement, masked))
    report["escalated"]["kept"] = "stronger" if better else "first"
    if better:
        shutil.rmtree(staging / "colmap", ignore_errors=True)
        (staging / "colmap_escalated").rename(staging / "colmap")
    shutil.rmtree(staging / "colmap_escalated", ignore_errors=True)
    return again if better else first
