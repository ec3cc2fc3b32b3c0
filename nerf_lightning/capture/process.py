"""A user's own capture, photos or a video, to a posed capture this project trains on: what ``nerf-process-data`` does.

    input (folder of photos | video)             [masks (folder, a mask a photo)]
      -> images/ (upright, full size) and images_2/, images_4/, images_8/          intake.py (images.py, video.py)
         [masks/ and masks_2/, masks_4/, masks_8/, lined up with them]             intake.py (images.py)
      -> COLMAP features (only on the masked object), matches, mapping, in-process through pycolmap
         (colmap.py, reconstruction.py); checked, and posed again with stronger settings where that falls short
                                                                                   posing.py, model_checks.py, silhouettes.py
      -> stopped with one line where the model cannot be used                      refusals.py
      -> transforms.json (nerfstudio's layout; frames with ``mask_path``), sparse_pc.ply, colmap/, report.json
                                                                                   output.py, report.py

Everything is written into a hidden folder beside ``output`` and moved into ``output`` at the end, transforms.json
last: a run that fails (bad images, too few registered, Ctrl-C) leaves ``output`` as it was and no
transforms.json without its images. A capture that COLMAP cannot pose well stops with one line that names the
images left out and what to change.
"""

from __future__ import annotations

import shutil
import tempfile
import time
from collections.abc import Sequence
from pathlib import Path
from typing import Any

from nerf_lightning.capture.colmap import choose_matcher, import_pycolmap
from nerf_lightning.capture.images import find_images, find_masks
from nerf_lightning.capture.intake import check_images, check_masks_apart, stage_images
from nerf_lightning.capture.output import publish, write_points_ply
from nerf_lightning.capture.posing import pose_capture
from nerf_lightning.capture.reconstruction import reconstruction_to_transforms, sparse_points
from nerf_lightning.capture.refusals import apply_pose_checks, check_silhouettes
from nerf_lightning.capture.report import masks_report, model_report
from nerf_lightning.capture.settings import CaptureSettings
from nerf_lightning.capture.video import VIDEO_SUFFIXES, is_video
from nerf_lightning.errors import ensure_writable
from nerf_lightning.io import write_json


def process_capture(input: str | Path, output: str | Path, frames: int = 100, matcher: str = "auto", mapper: str = "auto",
                    camera_model: str = "OPENCV", single_camera: bool = True, max_size: int = 1600, max_features: int = 8192,
                    downscales: Sequence[int] = (2, 4, 8), min_registered: float = 0.5, escalate: bool = True, seed: int = 0,
                    masks: str | Path | None = None, min_mask_agreement: float = 0.7, check_poses: bool = True,
                    mask_object: str = "white", progress: bool = True, verbose: bool = False) -> dict[str, Any]:
    """Pose a capture with COLMAP and write it as a nerfstudio capture into ``output`` (see the module's docstring).

    Args:
        input: a folder of photos (JPEG, PNG, TIFF, BMP, WebP; not its subfolders) or a video file.
        output: the folder to write; what an earlier run wrote there is replaced, anything else is kept.
        frames: for a video, how many frames to take, spread over the clip, the sharpest of each stretch.
        matcher: ``auto``, ``exhaustive`` (every pair) or ``sequential`` (neighbours in name or time order, and loop
            closures: the images that look most like each).
        mapper: ``auto`` (both of COLMAP's mappers, the model that explains the most verified matches kept),
            ``global`` (GLOMAP) or ``incremental`` (COLMAP's classic mapper).
        camera_model: COLMAP's lens model: OPENCV (k1, k2, p1, p2), SIMPLE_RADIAL, RADIAL, PINHOLE, SIMPLE_PINHOLE,
            or OPENCV_FISHEYE (k1 to k4: a GoPro's or a phone's ultra-wide lens).
        single_camera: all images share one camera's intrinsics (one phone, one zoom); false gives each its own.
        max_size: the long side in pixels the images are read at for feature extraction (images/ keeps full size).
        max_features: SIFT features an image.
        downscales: factors of the smaller copies, ``images_<k>/``.
        min_registered: stop with an error when COLMAP poses fewer than this fraction of the images.
        escalate: where fewer than :data:`~nerf_lightning.capture.posing.ESCALATE_BELOW` of the images register, or (with masks) the median photo's
            mask agrees with the poses less than :data:`~nerf_lightning.capture.posing.ESCALATE_AGREEMENT`, pose them
            again with stronger (slower) settings (:func:`~nerf_lightning.capture.posing.escalated_settings`), say so,
            and keep the better model (:func:`~nerf_lightning.capture.posing.model_score`).
        seed: COLMAP's random seed.
        masks: a folder with a mask for each photo, named as the photo (``IMG_1.jpg`` <- ``IMG_1.png``, or
            ``IMG_1.jpg.png``), of its size upright (EXIF orientation applied, as to the photos), any format Pillow
            reads; COLMAP then extracts features on the object alone, and the masks are written as ``masks/<stem>.png``
            (255 on the object) and ``masks_<k>/``, each frame of transforms.json naming its ``mask_path``. Not for a
            video.
        mask_object: which mask pixels are the object: ``white`` (at least half white; in a mask of 0s and 1s, the
            non-zero ones) or ``black`` (the rest).
        min_mask_agreement: with masks, stop with an error when the median photo's mask agrees with the model's
            poses less than this (:mod:`~nerf_lightning.capture.silhouettes`: the fraction of its mask's rays that
            meet the masks' visual hull); 0 keeps the model whatever it is.
        check_poses: act on the checks that need no masks (:func:`~nerf_lightning.capture.model_checks.pose_checks`):
            leave out the photos posed on too few of the model's points, stop where the model is wrong (its cameras
            spread far wider than they see, or a turntable's room standing still); false keeps whatever COLMAP posed,
            the report's ``pose_checks`` still saying what they found.
        progress: progress bars on stderr.
        verbose: COLMAP's own log on stderr.
    Returns:
        the report (also written as ``report.json``): images given and registered, those left out, mean reprojection
        error, mean track length, points, seconds of each stage; with masks, ``masks``: their folder, the convention,
        how many and the mean fraction of a photo that is object.
    """
    started = time.perf_counter()
    settings = CaptureSettings(frames=frames, matcher=matcher, mapper=mapper, camera_model=camera_model, single_camera=single_camera,
                               max_size=max_size, max_features=max_features, downscales=downscales, min_registered=min_registered,
                               escalate=escalate, seed=seed, min_mask_agreement=min_mask_agreement, check_poses=check_poses,
                               mask_object=mask_object, progress=progress, verbose=verbose)
    source, output = Path(input).expanduser(), Path(output).expanduser()
    mask_folder = Path(masks).expanduser() if masks not in (None, "") else None
    check_arguments(source, output, mask_folder, settings)
    import_pycolmap()  # before any work: a missing extra is the first thing to hear about
    photos = None if source.is_file() else find_images(source)
    photo_masks = None
    if mask_folder is not None:
        photo_masks = find_masks(mask_folder, photos)
        check_masks_apart(mask_folder, output)
    ensure_writable(output.parent, "output")
    staging = Path(tempfile.mkdtemp(prefix=f".{output.name}.", suffix=".partial", dir=output.parent))
    try:
        report = posed_capture(staging, source, output, photos, photo_masks, mask_folder, settings, started)
        publish(staging, output)
    finally:
        shutil.rmtree(staging, ignore_errors=True)
    return report


def check_arguments(source: Path, output: Path, mask_folder: Path | None, settings: CaptureSettings) -> None:
    """One clear error, before any work, where the input is missing or neither a folder nor a video, the output is a
    file, a setting is not one it can take (:meth:`~nerf_lightning.capture.settings.CaptureSettings.check`), or masks
    are given with a video."""
    if not source.exists():
        raise FileNotFoundError(f"input not found: {source} (expected a folder of images or a video file)")
    if source.is_file() and not is_video(source):
        raise ValueError(f"input {source} is a file but not a video ({', '.join(VIDEO_SUFFIXES)}); give a video or a folder of images")
    if output.exists() and not output.is_dir():
        raise NotADirectoryError(f"output must be a folder, got the file {output}")
    settings.check()
    if mask_folder is not None and source.is_file():
        raise ValueError(f"masks are not supported with a video input ({source.name}): give its frames as a folder of photos "
                         "with a mask each, or leave out masks=")


def posed_capture(staging: Path, source: Path, output: Path, photos: Sequence[Path] | None, masks: dict[Path, Path] | None,
                  mask_folder: Path | None, settings: CaptureSettings, started: float) -> dict[str, Any]:
    """Everything :func:`process_capture` writes, into ``staging``: the images of ``source`` (``photos``, or the
    video's frames) and their ``masks`` (photo -> mask file, from ``mask_folder``; or None), COLMAP's model of them
    (posed again with stronger settings where that falls short), transforms.json, sparse_pc.ply, colmap/ and
    report.json; returns the report. ValueError, one line, where the model cannot be used (:mod:`~nerf_lightning.capture.refusals`).
    ``started``: when the run started (``time.perf_counter()``), for its seconds."""
    seconds: dict[str, float] = {}
    report: dict[str, Any] = {"input": str(source), "output": str(output)}
    sizes, fractions = stage_images(source, photos, masks, staging, settings, report)
    seconds["images"] = time.perf_counter() - started
    check_images(source, sizes, settings.single_camera)
    names = list(sizes)
    chosen = choose_matcher(settings.matcher, len(names), source.is_file())
    kept = pose_capture(staging, names, sizes, chosen, bool(fractions), settings, seconds, report)
    left_out, unregistered = apply_pose_checks(kept, names, source, chosen, settings, "escalated" in report, report)

    write_started = time.perf_counter()
    transforms = reconstruction_to_transforms(kept.model, mask_folder="masks" if fractions else None, only=kept.posed)
    positions, colours = sparse_points(kept.model)
    write_points_ply(staging / transforms["ply_file_path"], positions, colours)
    seconds["writing"] = time.perf_counter() - write_started
    if fractions:
        report["silhouettes"] = kept.agreement
        check_silhouettes(kept.agreement, len(kept.posed), source, settings.min_mask_agreement)
    seconds["total"] = time.perf_counter() - started
    report.update(model_report(kept, names, sizes, unregistered, left_out, chosen, transforms, settings, seconds))
    if fractions:
        report["masks"] = masks_report(mask_folder, fractions, settings.mask_object)
    write_json(staging / "report.json", report)
    write_json(staging / "transforms.json", transforms)
    return report
