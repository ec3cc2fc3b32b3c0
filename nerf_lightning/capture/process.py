"""A user's own capture, photos or a video, to a posed capture this project trains on: what ``nerf-process-data`` does.

    input (folder of photos | video)             [masks (folder, a mask a photo)]
      -> images/ (upright, full size) and images_2/, images_4/, images_8/          images.py, video.py
         [masks/ and masks_2/, masks_4/, masks_8/, lined up with them]             images.py
      -> COLMAP features (only on the masked object), matches, mapping, in-process through pycolmap   colmap.py
      -> transforms.json (nerfstudio's layout; frames with ``mask_path``), sparse_pc.ply, colmap/, report.json

Everything is written into a hidden folder beside ``output`` and moved into ``output`` at the end, transforms.json
last: a run that fails (bad images, too few registered, Ctrl-C) leaves ``output`` as it was and no
transforms.json without its images. A capture that COLMAP cannot pose well stops with one line that names the
images left out and what to change.
"""

from __future__ import annotations

import logging
import math
import os
import re
import shutil
import tempfile
import time
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np
import trimesh
from PIL import Image
from tqdm import tqdm

from nerf_lightning.capture.colmap import (
    CAMERA_MODELS,
    MAPPERS,
    MATCHERS,
    choose_matcher,
    import_pycolmap,
    model_statistics,
    reconstruct,
    reconstruction_to_transforms,
    registered_names,
    sparse_points,
)
from nerf_lightning.capture.images import (
    MASK_OBJECTS,
    find_images,
    find_masks,
    listed,
    output_name,
    read_mask,
    save_image,
    write_capture_image,
    write_capture_mask,
    write_downscaled,
)
from nerf_lightning.capture.model_checks import MIN_POINTS, pose_checks
from nerf_lightning.capture.silhouettes import silhouette_agreement
from nerf_lightning.capture.video import VIDEO_SUFFIXES, is_video, pick_sharp_frames
from nerf_lightning.errors import ensure_writable
from nerf_lightning.io import write_atomic, write_json

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
    return None if agreement is None else agreement["median_coverage"]


def model_score(posed: set[str], agreement: dict[str, Any] | None, masks: bool) -> tuple[float, int]:
    """Which of two models of a capture to keep, the higher: the one with more photos posed, each weighted, where the
    capture has masks, by the masks' agreement with the poses (the median photo's), so that fewer photos posed right
    beat more posed partly wrong; on a tie, more photos posed. Under 3 posed, a model nothing can use: -1."""
    if len(posed) < 3:
        return (-1.0, len(posed))
    return (len(posed) * (agreement["median_coverage"] if masks and agreement is not None else 1.0), len(posed))


ADVICE = ("photos with more overlap (each part of the scene in 3 or more of them, taken a step apart, not turning on "
          "the spot), sharper ones (more light, steadier hands), a textured subject")


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


def write_photos(paths: Sequence[Path], staging: Path, downscales: Sequence[int], progress: bool) -> dict[str, tuple[int, int]]:
    """Each photo into ``staging/images`` and ``staging/images_<k>``; their names there and (width, height).
    ValueError naming the photos that cannot be read."""
    sizes, unreadable = {}, []
    for path in tqdm(paths, desc="images", unit="image", disable=not progress):
        try:
            name, size = write_capture_image(path, staging, downscales)
        except ValueError as error:
            unreadable.append(str(error))
            continue
        if name in sizes:
            raise ValueError(f"two inputs become images/{name} ({path.name} is one); rename one of them")
        sizes[name] = size
    if unreadable:
        shown = "; ".join(unreadable[:3]) + (f"; and {len(unreadable) - 3} more" if len(unreadable) > 3 else "")
        raise ValueError(f"could not read {len(unreadable)} of the {len(paths)} images in {paths[0].parent}: {shown}; "
                         "remove them or convert them to JPEG or PNG")
    return sizes


def write_video_frames(video: Path, staging: Path, count: int, downscales: Sequence[int], progress: bool) -> tuple[dict[str, tuple[int, int]], list[dict]]:
    """The sharpest frame of each of ``count`` stretches of ``video`` as ``frame_00001.jpg``, ... into
    ``staging/images`` and ``staging/images_<k>``; their names and sizes, and which video frames they are."""
    sizes = {}

    def write(frame: np.ndarray, number: int) -> None:
        name = f"frame_{number + 1:05d}.jpg"
        image = Image.fromarray(frame)
        save_image(image, staging / "images" / name)
        write_downscaled(image, name, staging, downscales)
        sizes[name] = image.size

    with tqdm(desc="video frames", unit="frame", disable=not progress) as bar:
        picked = pick_sharp_frames(video, count, write, progress=bar.update)
    for entry, name in zip(picked, sizes):
        entry["image"] = name
    return sizes, picked


def write_masks(masks: dict[Path, Path], sizes: dict[str, tuple[int, int]], staging: Path, downscales: Sequence[int],
                mask_object: str, progress: bool) -> dict[str, float]:
    """Each photo's mask (``masks``: photo -> mask file) into ``staging/masks`` and ``staging/masks_<k>``, and as
    COLMAP reads masks into ``staging/colmap/masks/<image name>.png``; of each image's name, the fraction of it that
    is object. ``sizes``: (width, height) of each image written, by name. ValueError, one line naming the masks that
    cannot be read, a mask of another size than its photo (both named, both sizes), one with no object in it or one
    that is all object."""
    fractions, unreadable = {}, []
    colmap_masks = staging / "colmap" / "masks"
    colmap_masks.mkdir(parents=True, exist_ok=True)
    for photo, path in tqdm(masks.items(), desc="masks", unit="mask", disable=not progress):
        name = output_name(photo)
        try:
            mask = read_mask(path, mask_object)
        except ValueError as error:
            unreadable.append(str(error))
            continue
        (width, height), (mask_height, mask_width) = sizes[name], mask.shape
        if (mask_width, mask_height) != (width, height):
            turned = " (drawn on the photo as stored, before its EXIF turn upright?)" if (mask_width, mask_height) == (height, width) else ""
            raise ValueError(f"mask {path.name} is {mask_width}x{mask_height} but its photo {photo.name} is {width}x{height} "
                             f"(upright){turned}; a mask must be its photo's size")
        if not mask.any():
            other = "black" if mask_object == "white" else "white"
            raise ValueError(f"mask {path.name} (of {photo.name}) is all background, nothing to match: no pixel of it is {mask_object} "
                             f"(mask_object={mask_object}); draw the object in it, or mask_object={other} if the masks mark the "
                             f"object {other}")
        if mask.all():
            other = "black" if mask_object == "white" else "white"
            raise ValueError(f"mask {path.name} (of {photo.name}) is all object, it leaves nothing out: every pixel of it is "
                             f"{mask_object} (mask_object={mask_object}); mask_object={other} if the masks mark the object "
                             f"{other}, or leave out masks= for photos with nothing to leave out")
        written = write_capture_mask(mask, name, staging, downscales)
        # COLMAP wants the mask as <image name>.png; a hard link costs nothing and leaves with colmap/masks
        try:
            os.link(written, colmap_masks / f"{name}.png")
        except OSError:
            shutil.copyfile(written, colmap_masks / f"{name}.png")
        fractions[name] = float(mask.mean())
    if unreadable:
        folder = next(iter(masks.values())).parent
        shown = "; ".join(unreadable[:3]) + (f"; and {len(unreadable) - 3} more" if len(unreadable) > 3 else "")
        raise ValueError(f"could not read {len(unreadable)} of the {len(masks)} masks in {folder}: {shown}; convert them to PNG")
    return fractions


def check_masks_apart(masks: Path, output: Path) -> None:
    """ValueError where the masks folder is one this run replaces in ``output`` (masks/, masks_<k>/): the masks would
    be deleted as the new ones are moved in."""
    resolved, replaced = masks.resolve(), output.resolve()
    if resolved.parent == replaced and (resolved.name == "masks" or MASKS_K.fullmatch(resolved.name)):
        raise ValueError(f"masks={masks} is inside the output, which this run replaces with the masks it writes; move them "
                         "out of it or write to another output")


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


def write_points_ply(path: Path, positions: np.ndarray, colours: np.ndarray) -> Path:
    """(P, 3) positions and (P, 3) uint8 RGB colours as a binary PLY point cloud (trimesh)."""
    cloud = trimesh.PointCloud(positions, colors=np.concatenate([colours, np.full((len(colours), 1), 255, np.uint8)], axis=1))
    return write_atomic(path, cloud.export(file_type="ply"))


MASKS_K = re.compile(r"masks_\d+")
# folders an earlier run wrote that this run may not write: removed, so that no images_8/ or masks/ of another run
# stays beside this run's transforms.json (a run without masks removes an earlier run's masks/: its frames name none)
STALE = re.compile(r"images_\d+|masks(_\d+)?")


def publish(staging: Path, output: Path) -> None:
    """Move what ``staging`` holds into ``output``, replacing what an earlier run wrote there: its transforms.json
    removed first and the new one moved in last, so that a transforms.json is never beside images of another run.
    An earlier run's ``images_<k>/``, ``masks/`` and ``masks_<k>/`` that this run did not write are removed too."""
    output.mkdir(parents=True, exist_ok=True)
    (output / "transforms.json").unlink(missing_ok=True)
    replaced = staging / ".replaced"
    replaced.mkdir()
    entries = [entry.name for entry in staging.iterdir() if entry.name not in ("transforms.json", ".replaced")]
    stale = [entry.name for entry in output.iterdir() if STALE.fullmatch(entry.name) and entry.name not in entries]
    for name in [*entries, *stale]:
        if (output / name).exists() or (output / name).is_symlink():
            os.replace(output / name, replaced / name)
        if name in entries:
            os.replace(staging / name, output / name)
    os.replace(staging / "transforms.json", output / "transforms.json")


def process_capture(
    input: str | Path,
    output: str | Path,
    frames: int = 100,
    matcher: str = "auto",
    mapper: str = "auto",
    camera_model: str = "OPENCV",
    single_camera: bool = True,
    max_size: int = 1600,
    max_features: int = 8192,
    downscales: Sequence[int] = (2, 4, 8),
    min_registered: float = 0.5,
    escalate: bool = True,
    seed: int = 0,
    masks: str | Path | None = None,
    min_mask_agreement: float = 0.7,
    check_poses: bool = True,
    mask_object: str = "white",
    progress: bool = True,
    verbose: bool = False,
) -> dict[str, Any]:
    """Pose a capture with COLMAP and write it as a nerfstudio capture into ``output`` (see the module's docstring).

    Args:
        input: a folder of photos (JPEG, PNG, TIFF, BMP, WebP; not its subfolders) or a video file.
        output: the folder to write; what an earlier run wrote there is replaced, anything else is kept.
        frames: for a video, how many frames to take, spread over the clip, the sharpest of each stretch.
        matcher: ``auto``, ``exhaustive`` (every pair) or ``sequential`` (neighbours in name or time order, and loop
            closures: the images that look most like each).
        mapper: ``auto`` (both of COLMAP's mappers, the model that explains the most verified matches kept),
            ``global`` (GLOMAP) or ``incremental`` (COLMAP's classic mapper).
        camera_model: COLMAP's lens model: OPENCV (k1, k2, p1, p2), SIMPLE_RADIAL, RADIAL, PINHOLE, SIMPLE_PINHOLE.
        single_camera: all images share one camera's intrinsics (one phone, one zoom); false gives each its own.
        max_size: the long side in pixels the images are read at for feature extraction (images/ keeps full size).
        max_features: SIFT features an image.
        downscales: factors of the smaller copies, ``images_<k>/``.
        min_registered: stop with an error when COLMAP poses fewer than this fraction of the images.
        escalate: where fewer than :data:`ESCALATE_BELOW` of the images register, or (with masks) the median photo's
            mask agrees with the poses less than :data:`ESCALATE_AGREEMENT`, pose them again with stronger (slower)
            settings (:func:`escalated_settings`), say so, and keep the better model (:func:`model_score`).
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
    source, output = Path(input).expanduser(), Path(output).expanduser()
    if not source.exists():
        raise FileNotFoundError(f"input not found: {source} (expected a folder of images or a video file)")
    if source.is_file() and not is_video(source):
        raise ValueError(f"input {source} is a file but not a video ({', '.join(VIDEO_SUFFIXES)}); give a video or a folder of images")
    if output.exists() and not output.is_dir():
        raise NotADirectoryError(f"output must be a folder, got the file {output}")
    if matcher not in MATCHERS:
        raise ValueError(f"matcher must be one of {', '.join(MATCHERS)}, got '{matcher}'")
    if mapper not in MAPPERS:
        raise ValueError(f"mapper must be one of {', '.join(MAPPERS)}, got '{mapper}'")
    if camera_model not in CAMERA_MODELS:
        raise ValueError(f"camera_model must be one of {', '.join(CAMERA_MODELS)}, got '{camera_model}'")
    if int(max_size) < 64:
        raise ValueError(f"max_size must be at least 64 pixels, got {max_size}")
    if any(int(factor) != factor or factor < 2 for factor in downscales):
        raise ValueError(f"downscales must be integers of 2 or more, got {list(downscales)}")
    if not 0.0 <= min_registered <= 1.0:
        raise ValueError(f"min_registered must be a fraction between 0 and 1, got {min_registered}")
    if mask_object not in MASK_OBJECTS:
        raise ValueError(f"mask_object must be {' or '.join(MASK_OBJECTS)}, got '{mask_object}'")
    if not 0.0 <= min_mask_agreement <= 1.0:
        raise ValueError(f"min_mask_agreement must be a fraction between 0 and 1, got {min_mask_agreement}")
    mask_folder = Path(masks).expanduser() if masks not in (None, "") else None
    if mask_folder is not None and source.is_file():
        raise ValueError(f"masks are not supported with a video input ({source.name}): give its frames as a folder of photos "
                         "with a mask each, or leave out masks=")
    pycolmap = import_pycolmap()  # before any work: a missing extra is the first thing to hear about
    from_video = source.is_file()
    images_given = None if from_video else find_images(source)
    photo_masks = None
    if mask_folder is not None:
        photo_masks = find_masks(mask_folder, images_given)
        check_masks_apart(mask_folder, output)
    ensure_writable(output.parent, "output")
    staging = Path(tempfile.mkdtemp(prefix=f".{output.name}.", suffix=".partial", dir=output.parent))
    try:
        seconds: dict[str, float] = {}
        report: dict[str, Any] = {"input": str(source), "output": str(output)}
        if from_video:
            sizes, report["video_frames"] = write_video_frames(source, staging, frames, downscales, progress)
        else:
            sizes = write_photos(images_given, staging, downscales, progress)
        fractions = write_masks(photo_masks, sizes, staging, downscales, mask_object, progress) if photo_masks else None
        seconds["images"] = time.perf_counter() - started
        names = list(sizes)
        if len(names) < 3:
            raise ValueError(f"{source} gave {len(names)} image{'s' if len(names) != 1 else ''}; structure from motion needs 3 or more "
                             "(20 to 100 overlapping photos work well)")
        if single_camera and len(set(sizes.values())) > 1:
            first = names[0]
            other = next(name for name in names if sizes[name] != sizes[first])
            raise ValueError(f"the images are not all one size ({first} {sizes[first][0]}x{sizes[first][1]}, {other} "
                             f"{sizes[other][0]}x{sizes[other][1]}); use single_camera=false (a camera each) or resize them alike")

        chosen = choose_matcher(matcher, len(names), from_video)
        model, stage_seconds, mapping = reconstruct(
            staging / "images", names, staging / "colmap", matcher=chosen, mapper=mapper, camera_model=camera_model, single_camera=single_camera,
            max_size=int(max_size), max_features=int(max_features), seed=seed,
            masks=staging / "colmap" / "masks" if fractions else None, progress=progress, verbose=verbose)
        def agreement_with(candidate: Any, candidate_posed: set[str]) -> dict[str, Any] | None:
            """With masks, their agreement with a model's poses (:func:`model_agreement`), its seconds counted."""
            if not fractions:
                return None
            check_started = time.perf_counter()
            found = model_agreement(candidate, candidate_posed, staging, downscales, seed)
            seconds["silhouettes"] = seconds.get("silhouettes", 0.0) + time.perf_counter() - check_started
            return found

        def checked(candidate: Any, colmap_dir: Path, other: Any) -> tuple[dict[str, Any] | None, set[str]]:
            """A model's pose checks (:func:`~nerf_lightning.capture.model_checks.pose_checks`; None without a model)
            and the photos it poses that they hold in place (all it registered with ``check_poses=false``)."""
            if candidate is None:
                return None, set()
            found = pose_checks(colmap_dir / "database.db", candidate, other)
            return found, registered_names(candidate) - (set(found["thinly_posed"]) if check_poses else set())

        checks, posed = checked(model, staging / "colmap", mapping["other_model"])
        refused = bool(check_poses and checks and checks["refuse"])
        agreement = agreement_with(model, posed)
        too_few = len(posed) < ESCALATE_BELOW * len(names) or refused
        # a model that would stop on min_mask_agreement is tried again too, where that is set above ESCALATE_AGREEMENT
        disagree = agreement is not None and agreement["median_coverage"] < max(ESCALATE_AGREEMENT, min_mask_agreement)
        if escalate and (too_few or disagree):
            stronger = escalated_settings(int(max_size), int(max_features), sizes)
            again_matcher = stronger_matcher(len(names))
            why = (f"COLMAP's model is wrong: {checks['refuse'][0].split(';')[0]}" if refused else
                   f"COLMAP posed {len(posed)} of the {len(names)} images" if too_few else
                   f"the masks agree with the poses in {100.0 * agreement['median_coverage']:.0f}% of the median photo's rays")
            log.warning("%s (%s); posing them again with stronger settings: features at %d px, %d of them, affine shapes and "
                        "domain-size pooling, guided matching, %s (slower)", why, matches_said(mapping["matches"]),
                        stronger["max_size"], stronger["max_features"],
                        "on every pair" if again_matcher == "exhaustive" else
                        "on the pairs that can overlap (neighbours in name order, the photos most alike, the pairs verified already)")
            again, again_seconds, again_mapping = reconstruct(
                staging / "images", names, staging / "colmap_escalated", matcher=again_matcher, mapper=mapper, camera_model=camera_model,
                single_camera=single_camera, seed=seed, masks=staging / "colmap" / "masks" if fractions else None, progress=progress,
                verbose=verbose, verified_in=staging / "colmap" / "database.db", **stronger)
            again_checks, again_posed = checked(again, staging / "colmap_escalated", again_mapping["other_model"])
            again_refused = bool(check_poses and again_checks and again_checks["refuse"])
            again_agreement = agreement_with(again, again_posed)
            report["escalated"] = {"why": "model" if refused else "registered" if too_few else "masks", "registered_before": len(posed),
                                   "matches_before": mapping["matches"], "matches_after": again_mapping["matches"],
                                   "registered_after": len(again_posed), "matcher": again_matcher,
                                   "settings": {key: value for key, value in stronger.items() if key != "strong"},
                                   "seconds": round(sum(again_seconds.values()), 2)}
            if fractions:
                report["escalated"].update({"mask_agreement_before": agreement_of(agreement),
                                            "mask_agreement_after": agreement_of(again_agreement)})
            seconds["escalation"] = sum(again_seconds.values())
            # a model the checks refuse is never kept over one they do not
            better = (not again_refused, model_score(again_posed, again_agreement, bool(fractions))) > \
                     (not refused, model_score(posed, agreement, bool(fractions)))
            report["escalated"]["kept"] = "stronger" if better else "first"
            if better:
                shutil.rmtree(staging / "colmap", ignore_errors=True)
                (staging / "colmap_escalated").rename(staging / "colmap")
                model, mapping, posed, agreement, checks = again, again_mapping, again_posed, again_agreement, again_checks
            shutil.rmtree(staging / "colmap_escalated", ignore_errors=True)
        shutil.rmtree(staging / "colmap" / "masks", ignore_errors=True)  # masks/ holds them, by the photos' names
        seconds.update(stage_seconds)
        left_out = []
        if checks is not None:  # (no model: the registration check below says so)
            report["pose_checks"] = checks
            if check_poses and checks["refuse"]:
                raise ValueError(f"COLMAP registered {len(posed)} images of {source}, but its model is wrong: "
                                 + "; ".join(checks["refuse"]) + "; or check_poses=false to keep this model")
            for said in checks["warn"] + ([] if check_poses else checks["refuse"]):
                log.warning("%s", said)
            left_out = sorted(set(checks["thinly_posed"]) - posed)
        unregistered = [name for name in names if name not in posed and name not in left_out]
        check_registered(len(posed), unregistered, len(names), source, chosen, min_registered, escalated="escalated" in report,
                         left_out=left_out)

        write_started = time.perf_counter()
        transforms = reconstruction_to_transforms(model, mask_folder="masks" if fractions else None, only=posed)
        positions, colours = sparse_points(model)
        write_points_ply(staging / transforms["ply_file_path"], positions, colours)
        seconds["writing"] = time.perf_counter() - write_started
        if fractions:
            report["silhouettes"] = agreement
            check_silhouettes(agreement, len(posed), source, min_mask_agreement)
        seconds["total"] = time.perf_counter() - started
        report.update({
            "images_given": len(names), "registered": len(posed), "unregistered": unregistered, "left_out": left_out, "matcher": chosen,
            "mapper": mapping["mapper"], "mappers": mapping["mappers"], "matches": mapping["matches"],
            "focal_priors": mapping["focal_priors"],
            "verified_matches_explained": mapping["mappers"][mapping["mapper"]]["verified_matches_explained"],
            "camera_model": camera_model, "single_camera": bool(single_camera), "max_size": int(max_size),
            "photo_side": max(max(size) for size in sizes.values()),
            **model_statistics(model),
            "camera": {key: transforms[key] for key in ("fl_x", "fl_y", "cx", "cy", "k1", "k2", "p1", "p2", "w", "h") if key in transforms},
            "seconds": {stage: round(value, 2) for stage, value in seconds.items()},
            "pycolmap": getattr(pycolmap, "__version__", "unknown"),
        })
        if fractions:
            report["masks"] = {"folder": str(mask_folder), "mask_object": mask_object, "count": len(fractions),
                               "mean_object_fraction": round(float(np.mean(list(fractions.values()))), 4)}
        write_json(staging / "report.json", report)
        write_json(staging / "transforms.json", transforms)
        publish(staging, output)
    finally:
        shutil.rmtree(staging, ignore_errors=True)
    return report


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
