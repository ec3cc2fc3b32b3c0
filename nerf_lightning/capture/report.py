"""``nerf-process-data``'s report: what report.json holds of the model kept (:func:`model_report`), and the few lines
the command prints of it (:func:`format_report`), ending with the commands that train on the capture.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

from nerf_lightning.capture.colmap import import_pycolmap
from nerf_lightning.capture.images import listed
from nerf_lightning.capture.model_checks import MIN_POINTS
from nerf_lightning.capture.posing import PosingPass
from nerf_lightning.capture.reconstruction import model_statistics
from nerf_lightning.capture.settings import CaptureSettings


def model_report(kept: PosingPass, names: Sequence[str], sizes: dict[str, tuple[int, int]], unregistered: list[str], left_out: list[str],
                 matcher: str, transforms: dict[str, Any], settings: CaptureSettings, seconds: dict[str, float]) -> dict[str, Any]:
    """report.json's entries of the model kept: the images given (``names``, of (width, height) ``sizes``), those
    registered, not registered and left out, the ``matcher`` and mapper, what matching left, the camera written to
    ``transforms``, the model's statistics, the ``seconds`` of each stage and pycolmap's version."""
    mapping = kept.mapping
    return {
        "images_given": len(names), "registered": len(kept.posed), "unregistered": unregistered, "left_out": left_out, "matcher": matcher,
        "mapper": mapping["mapper"], "mappers": mapping["mappers"], "matches": mapping["matches"],
        "focal_priors": mapping["focal_priors"],
        "verified_matches_explained": mapping["mappers"][mapping["mapper"]]["verified_matches_explained"],
        "camera_model": settings.camera_model, "single_camera": bool(settings.single_camera), "max_size": int(settings.max_size),
        "photo_side": max(max(size) for size in sizes.values()),
        **model_statistics(kept.model),
        "camera": {key: transforms[key] for key in ("fl_x", "fl_y", "cx", "cy", "k1", "k2", "k3", "k4", "p1", "p2", "w", "h") if key in transforms},
        "seconds": {stage: round(value, 2) for stage, value in seconds.items()},
        "pycolmap": getattr(import_pycolmap(), "__version__", "unknown"),
    }


def masks_report(folder: Path, fractions: dict[str, float], mask_object: str) -> dict[str, Any]:
    """report.json's ``masks``: their ``folder``, the colour that is object, how many, and the mean fraction of a
    photo that is object (``fractions``: of each image's name)."""
    return {"folder": str(folder), "mask_object": mask_object, "count": len(fractions),
            "mean_object_fraction": round(float(np.mean(list(fractions.values()))), 4)}


# the object presets' views: the photos area-averaged by the smallest whole factor that brings their long side to at
# most this (a CPU's 10 minutes; transforms.json's loader averages the full-size photos and masks by any factor), and
# patches of data.patch_size=PATCH_SIZE where that side is still over PATCH_OVER (conf/experiment/splat_object_cpu.yaml)
TRAIN_SIDE = 1024
PATCH_OVER = 500
PATCH_SIZE = 384


def next_commands(report: dict[str, Any]) -> list[str]:
    """The commands that train on the capture, the report's last lines: a masked capture's object alone, as splats
    and as a NeRF in its box, on views of about a thousand pixels a side; else the capture with its background."""
    output = report["output"]
    if not report.get("masks"):
        return [f"next: nerf-train experiment=fast_unbounded data.root={output}"]
    side = report.get("photo_side")
    sized = patches = ""  # a report from before photo_side: the presets' own downscale
    if side is not None:
        factor = max(1, math.ceil(side / TRAIN_SIDE))
        sized = f" data.scene.downscale={factor}"
        patches = f" data.patch_size={PATCH_SIZE}" if side / factor > PATCH_OVER else ""
    return [f"next: nerf-train experiment=splat_object_cpu data.root={output}{sized}{patches}",
            f"  or a NeRF of the object in its box: nerf-train experiment=nerfacto_object_cpu data.root={output}{sized}"]


def format_report(report: dict[str, Any]) -> str:
    """The report as the few lines ``nerf-process-data`` prints."""
    given, registered = report["images_given"], report["registered"]
    output, masks = report["output"], report.get("masks")
    lines = [
        f"registered {registered} of {given} images ({100.0 * registered / given:.0f}%; {report['matcher']} matching, {report['mapper']} mapping, "
        f"{report['camera_model']} camera{'' if report['single_camera'] else 's'})",
        f"mean reprojection error {report['mean_reprojection_error_px']:.2f} px, mean track length {report['mean_track_length']:.1f} "
        f"images, {report['points']} points; the poses explain {100.0 * report['verified_matches_explained']:.0f}% of the verified matches",
        "did not register: " + (listed(report["unregistered"]) if report["unregistered"] else "none"),
        f"{report['seconds']['total']:.0f} s: " + ", ".join(f"{stage} {value:.0f} s" for stage, value in report["seconds"].items() if stage != "total"),
        f"wrote {output}/transforms.json, images/ (and smaller copies), {'masks/ (and smaller copies), ' if masks else ''}"
        "sparse_pc.ply, colmap/, report.json",
        *next_commands(report),
    ]
    if "escalated" in report:
        escalated = report["escalated"]
        if escalated.get("why") == "masks":
            first = f"the masks agreed {100.0 * escalated['mask_agreement_before']:.0f}% at first"
            after = f"{escalated['registered_after']} and agreed " + (
                f"{100.0 * escalated['mask_agreement_after']:.0f}%" if escalated["mask_agreement_after"] is not None else "not at all")
        elif escalated.get("why") == "model":
            first, after = "the pose checks refused the first model", f"{escalated['registered_after']}"
        else:
            first, after = f"too few registered at first ({escalated['registered_before']})", f"{escalated['registered_after']}"
        lines.insert(1, f"{first}: posed again with stronger settings ({escalated['settings']['max_size']} px, "
                        f"{escalated['settings']['max_features']} features, affine shapes, guided matching), which registered {after}; "
                        + ("that model is kept" if escalated.get("kept", "stronger") == "stronger" else "the first model is kept"))
    for prior in report.get("focal_priors", []):
        lines.insert(2, f"focal length from {prior['image']}'s EXIF read for its own size: {prior['set_px']:.0f} px (COLMAP read "
                        f"{prior['colmap_px']:.0f} px, as if for the camera's full frame: the photo was downscaled or cropped)")
    if masks:
        lines.insert(3, f"masks: {masks['count']} from {masks['folder']} ({masks['mask_object']} = object), on average "
                        f"{100.0 * masks['mean_object_fraction']:.0f}% of a photo; features matched on the object alone")
    if report.get("left_out"):
        lines.insert(3, f"left out, posed on fewer than {MIN_POINTS} of the model's points: {listed(report['left_out'])}")
    repeated = (report.get("pose_checks") or {}).get("repeated")
    if repeated:
        lines.insert(3, "one picture twice (their matches do not move): " + "; ".join(" and ".join(pair) for pair in repeated))
    if "silhouettes" in report:
        agreement = report["silhouettes"]
        below = agreement["views_below"]
        lines.insert(4, f"masks and poses agree: in the median photo {100.0 * agreement['median_coverage']:.0f}% of the mask's rays meet "
                        "the object the masks carve" + (f"; under half in {listed(below)} (posed wrong, or a mask that does not fit "
                                                        "its photo)" if below else ""))
    return "\n".join(lines)
