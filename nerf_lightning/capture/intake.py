"""The images in: a capture's photos (or a video's sharpest frames) and their masks written into the staging folder
``nerf-process-data`` builds its output in (:mod:`~nerf_lightning.capture.process`), as COLMAP and the loaders read
them, and the checks that stop a run before COLMAP starts.

    staging/images/ (upright, full size) and images_2/, images_4/, images_8/        images.py, video.py
    [staging/masks/ and masks_2/, masks_4/, masks_8/, lined up with them]            images.py
    [staging/colmap/masks/<image name>.png: the masks as COLMAP reads them]
"""

from __future__ import annotations

import os
import re
import shutil
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np
from PIL import Image
from tqdm import tqdm

from nerf_lightning.capture.images import output_name, read_mask, save_image, write_capture_image, write_capture_mask, write_downscaled
from nerf_lightning.capture.settings import CaptureSettings
from nerf_lightning.capture.video import pick_sharp_frames


def stage_images(source: Path, photos: Sequence[Path] | None, masks: dict[Path, Path] | None, staging: Path, settings: CaptureSettings,
                 report: dict[str, Any]) -> tuple[dict[str, tuple[int, int]], dict[str, float] | None]:
    """The capture's images into ``staging`` (:func:`write_photos` of ``photos``, or where ``source`` is a video,
    :func:`write_video_frames`, which of its frames they are then in ``report["video_frames"]``), and their ``masks``
    (photo -> mask file, or None; :func:`write_masks`). Returns each image's (width, height) by its name, and of each
    the fraction that is object (None without masks)."""
    if source.is_file():
        sizes, report["video_frames"] = write_video_frames(source, staging, settings.frames, settings.downscales, settings.progress)
    else:
        sizes = write_photos(photos, staging, settings.downscales, settings.progress)
    fractions = write_masks(masks, sizes, staging, settings.downscales, settings.mask_object, settings.progress) if masks else None
    return sizes, fractions


def check_images(source: Path, sizes: dict[str, tuple[int, int]], single_camera: bool) -> None:
    """ValueError, one line, where the images written (``sizes``: (width, height) by name) are too few to pose, or not
    all one size where they are to share one camera (``single_camera``)."""
    names = list(sizes)
    if len(names) < 3:
        raise ValueError(f"{source} gave {len(names)} image{'s' if len(names) != 1 else ''}; structure from motion needs 3 or more "
                         "(20 to 100 overlapping photos work well)")
    if single_camera and len(set(sizes.values())) > 1:
        first = names[0]
        other = next(name for name in names if sizes[name] != sizes[first])
        raise ValueError(f"the images are not all one size ({first} {sizes[first][0]}x{sizes[first][1]}, {other} "
                         f"{sizes[other][0]}x{sizes[other][1]}); use single_camera=false (a camera each) or resize them alike")


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


MASKS_K = re.compile(r"masks_\d+")


def check_masks_apart(masks: Path, output: Path) -> None:
    """ValueError where the masks folder is one this run replaces in ``output`` (masks/, masks_<k>/): the masks would
    be deleted as the new ones are moved in."""
    resolved, replaced = masks.resolve(), output.resolve()
    if resolved.parent == replaced and (resolved.name == "masks" or MASKS_K.fullmatch(resolved.name)):
        raise ValueError(f"masks={masks} is inside the output, which this run replaces with the masks it writes; move them "
                         "out of it or write to another output")
