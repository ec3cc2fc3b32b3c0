"""A capture's photos, made ready for structure from motion and for training: turned upright by their EXIF
orientation, written to ``images/`` at full resolution and to ``images_<k>/`` downscaled k times (nerfstudio's layout).
Their masks, where given, likewise to ``masks/<photo stem>.png`` and ``masks_<k>/``: 8-bit grey, 255 where the photo
shows the object and 0 elsewhere (nerfstudio's convention: a non-zero mask pixel keeps its image pixel).

A phone stores a portrait photo as landscape pixels plus an EXIF tag saying how to turn it; COLMAP and this
project's loaders read the pixels as stored, so the pixels themselves are turned here, once.
"""

from __future__ import annotations

import io
import math
import re
import shutil
from collections.abc import Iterable, Sequence
from pathlib import Path

import numpy as np
import torch
from PIL import Image, ImageOps

from nerf_lightning.capture.choices import MASK_OBJECTS
from nerf_lightning.data.images import downscale_mask, mask_channel, white_pixels
from nerf_lightning.io import write_atomic

# read by Pillow; HEIC/HEIF (iPhones) is listed so that such files are named as unreadable rather than silently left out
IMAGE_SUFFIXES = (".jpg", ".jpeg", ".png", ".tif", ".tiff", ".bmp", ".webp", ".heic", ".heif")
EXIF_ORIENTATION = 0x0112
# the EXIF sub-IFD and the tags a focal length in pixels is read from
EXIF_IFD, FOCAL_LENGTH, FOCAL_LENGTH_35MM = 0x8769, 0x920A, 0xA405
PIXEL_X, PIXEL_Y, FOCAL_PLANE_X_RESOLUTION, FOCAL_PLANE_UNIT = 0xA002, 0xA003, 0xA20E, 0xA210
# FocalPlaneResolutionUnit: 2 inches, 3 centimetres, 4 millimetres, 5 micrometres (1 and absent: inches, in practice)
MILLIMETRES_A_UNIT = {1: 25.4, 2: 25.4, 3: 10.0, 4: 1.0, 5: 0.001}
JPEG_QUALITY = 95
# which mask pixels are the object: white (at least half white; non-zero in a mask of 0s and 1s) or black


def natural_key(name: str) -> list:
    """Sort key that orders numbered names as a person would: IMG_2 before IMG_10."""
    return [int(part) if part.isdigit() else part.lower() for part in re.split(r"(\d+)", name)]


def find_images(folder: Path) -> list[Path]:
    """The image files directly in ``folder``, in natural name order; ValueError naming the folder when there are none."""
    if not folder.is_dir():
        raise NotADirectoryError(f"input must be a folder of images or a video file, got {folder}")
    paths = sorted((path for path in folder.iterdir() if path.is_file() and path.suffix.lower() in IMAGE_SUFFIXES), key=lambda p: natural_key(p.name))
    if not paths:
        raise ValueError(f"no images in {folder} (expected files ending in {', '.join(IMAGE_SUFFIXES[:4])}, ...); "
                         f"for a video give the file itself: input=<video.mp4>")
    return paths


def upright(image: Image.Image) -> Image.Image:
    """The image turned as its EXIF orientation tag says (the tag dropped); unchanged without one."""
    return ImageOps.exif_transpose(image)


def orientation(image: Image.Image) -> int:
    """The EXIF orientation tag, 1 (as stored) when absent."""
    return int(image.getexif().get(EXIF_ORIENTATION, 1) or 1)


def exif_focal_length(path: Path) -> float | None:
    """The focal length in pixels of the photo at ``path`` as its pixels are now, from its EXIF; None without one.

    The camera wrote its EXIF for the sensor's full frame (``PixelXDimension`` x ``PixelYDimension``). A photo
    downscaled or cropped since, with its EXIF kept, has other pixels: COLMAP's own reading (the focal length in mm
    times the focal plane's pixels a mm) then gives the full frame's focal length, several times too long for a
    downscaled copy, and its mapper fails on it. Here it is scaled by the short side's ratio, which is right for a
    downscale and for a crop that keeps the short side (a square crop of a 3:2 frame); an arbitrary crop cannot be
    told apart. Read from the focal length in mm and the focal plane's resolution, or else from the 35 mm equivalent
    (36 mm across the frame's long side)."""
    try:
        with Image.open(path) as opened:
            width, height = upright(opened).size if orientation(opened) != 1 else opened.size
            tags = opened.getexif().get_ifd(EXIF_IFD)
    except Exception:  # unreadable EXIF: COLMAP's own guess stands
        return None

    def number(tag: int) -> float | None:
        try:
            value = float(tags.get(tag) or 0.0)
        except (TypeError, ValueError, ZeroDivisionError):
            return None
        return value if math.isfinite(value) and value > 0 else None

    frame = (number(PIXEL_X), number(PIXEL_Y))
    frame_short, frame_long = (min(frame), max(frame)) if None not in frame else (float(min(width, height)), float(max(width, height)))
    millimetres, density = number(FOCAL_LENGTH), number(FOCAL_PLANE_X_RESOLUTION)
    unit = MILLIMETRES_A_UNIT.get(int(tags.get(FOCAL_PLANE_UNIT) or 2))
    if millimetres is not None and density is not None and unit is not None:
        full_frame = millimetres * density / unit
    elif number(FOCAL_LENGTH_35MM) is not None:
        full_frame = number(FOCAL_LENGTH_35MM) / 36.0 * frame_long
    else:
        return None
    return full_frame * min(width, height) / frame_short


def save_image(image: Image.Image, path: Path) -> Path:
    """Write ``image`` as JPEG (quality 95) or PNG by ``path``'s suffix, atomically, keeping its EXIF (focal length)."""
    if image.mode not in ("RGB", "L", "RGBA") or (image.mode == "RGBA" and path.suffix.lower() != ".png"):
        image = image.convert("RGB")
    buffer = io.BytesIO()
    exif = image.getexif()
    if path.suffix.lower() in (".jpg", ".jpeg"):
        image.save(buffer, format="JPEG", quality=JPEG_QUALITY, exif=exif)
    else:
        image.save(buffer, format="PNG", exif=exif)
    return write_atomic(path, buffer.getvalue())


def write_downscaled(image: Image.Image, name: str, output: Path, downscales: Iterable[int]) -> None:
    """``output/images_<k>/<name>`` for each k: ``image`` (already upright) area-averaged over k x k blocks, the
    remainder rows and columns cropped (as :func:`nerf_lightning.data.images.downscale` does)."""
    width, height = image.size
    for factor in downscales:
        if width // factor < 1 or height // factor < 1:
            raise ValueError(f"downscale {factor} is larger than the image {name} ({width}x{height})")
        smaller = image.crop((0, 0, width // factor * factor, height // factor * factor)).reduce(factor)
        smaller.info = image.info
        save_image(smaller, output / f"images_{factor}" / name)


def output_name(path: Path) -> str:
    """The name a photo gets in ``images/``: its own for JPEG and PNG, with ``.png`` for the other formats."""
    return path.name if path.suffix.lower() in (".jpg", ".jpeg", ".png") else path.with_suffix(".png").name


def write_capture_image(path: Path, output: Path, downscales: Iterable[int]) -> tuple[str, tuple[int, int]]:
    """One photo into ``output/images/`` (upright) and ``output/images_<k>/``.

    A JPEG or PNG stored upright is copied byte for byte; any other is decoded, turned and encoded again.
    Returns the name it got and its (width, height) upright. Raises ValueError naming the file when Pillow
    cannot read it.
    """
    name = output_name(path)
    try:
        with Image.open(path) as opened:
            opened.load()
            stored_upright = orientation(opened) == 1 and opened.format in ("JPEG", "PNG") and name == path.name
            image = upright(opened)
    except Exception as error:  # Pillow raises many types for unknown, corrupt and truncated files
        raise ValueError(f"{path.name} ({error})") from error
    if stored_upright:
        (output / "images").mkdir(parents=True, exist_ok=True)
        shutil.copyfile(path, output / "images" / name)
    else:
        save_image(image, output / "images" / name)
    write_downscaled(image, name, output, downscales)
    return name, image.size


def listed(names: Sequence[str], shown: int = 8) -> str:
    return ", ".join(names[:shown]) + (f" and {len(names) - shown} more" if len(names) > shown else "")


def find_masks(folder: Path, photos: Sequence[Path]) -> dict[Path, Path]:
    """Each photo's mask in ``folder``, matched by name: ``IMG_1.jpg``'s is ``IMG_1.<any image suffix>`` or
    nerfstudio's and COLMAP's ``IMG_1.jpg.png``.

    Raises FileNotFoundError or NotADirectoryError naming ``folder``, and ValueError naming the photos without a mask
    or with two, or two photos of one stem (their masks would be one ``masks/<stem>.png``). Masks without a photo are left alone (a capture pruned of its blurred photos keeps its masks folder).
    """
    if not folder.exists():
        raise FileNotFoundError(f"masks folder not found: {folder} (expected a folder with a mask for each photo, "
                                "named as the photo: IMG_1.jpg <- IMG_1.png)")
    if not folder.is_dir():
        raise NotADirectoryError(f"masks must be a folder with a mask for each photo, got the file {folder}")
    if photos and folder.resolve() == photos[0].parent.resolve():
        raise ValueError(f"masks={folder} is the photos' own folder: the photos would be their own masks; put the masks in "
                         "a folder of their own")
    stems: dict[str, str] = {}
    for photo in photos:
        if photo.stem in stems:
            raise ValueError(f"photos {stems[photo.stem]} and {photo.name} would share the mask masks/{photo.stem}.png; rename one")
        stems[photo.stem] = photo.name
    readable = {suffix.lower() for suffix in Image.registered_extensions()} | set(IMAGE_SUFFIXES)
    by_stem: dict[str, list[Path]] = {}
    for path in sorted(folder.iterdir(), key=lambda p: natural_key(p.name)):
        if path.is_file() and path.suffix.lower() in readable and not path.name.startswith("."):
            by_stem.setdefault(path.stem, []).append(path)
    masks, missing = {}, []
    for photo in photos:
        found = by_stem.get(photo.stem, []) + by_stem.get(photo.name, [])
        if len(found) > 1:
            raise ValueError(f"{photo.name} has {len(found)} masks in {folder} ({', '.join(path.name for path in found)}); keep one")
        if not found:
            missing.append(photo.name)
            continue
        masks[photo] = found[0]
    if missing:
        raise ValueError(f"{len(missing)} of the {len(photos)} photos have no mask in {folder}: {listed(missing)}; a mask is "
                         f"named as its photo, {Path(missing[0]).stem}.png (or {missing[0]}.png)")
    return masks


def mask_values(image: Image.Image) -> np.ndarray:
    """(H, W) values of a mask image: its alpha where that varies, else its first channel, as
    :func:`nerf_lightning.data.images.load_mask` reads a mask."""
    if image.mode == "P":
        image = image.convert("RGBA" if "transparency" in image.info else "RGB")
    elif image.mode not in ("1", "L", "LA", "RGB", "RGBA", "I;16", "I", "F"):
        image = image.convert("RGB")
    return mask_channel(np.asarray(image))


def read_mask(path: Path, mask_object: str = "white") -> np.ndarray:
    """A mask file as (H, W) bool, True on the object, turned upright by its EXIF orientation as the photos are.

    With ``mask_object="white"`` the object is where the mask is at least half white (128 and up of 255: JPEG noise
    around black and white stays put), or non-zero in a mask of 0s and 1s; ``"black"`` is the inverse. Raises
    ValueError naming the file when Pillow cannot read it.
    """
    if mask_object not in MASK_OBJECTS:
        raise ValueError(f"mask_object must be {' or '.join(MASK_OBJECTS)}, got '{mask_object}'")
    try:
        with Image.open(path) as opened:
            opened.load()
            values = mask_values(upright(opened))
    except Exception as error:  # Pillow raises many types for unknown, corrupt and truncated files
        raise ValueError(f"{path.name} ({error})") from error
    white = white_pixels(values)
    return white if mask_object == "white" else ~white


def mask_name(image_name: str) -> str:
    """The name a photo's mask gets in ``masks/``: the photo's stem with ``.png`` (IMG_1.jpg -> IMG_1.png)."""
    return f"{Path(image_name).stem}.png"


def write_capture_mask(mask: np.ndarray, image_name: str, output: Path, downscales: Iterable[int]) -> Path:
    """(H, W) bool object mask of the photo ``images/<image_name>`` as ``output/masks/<stem>.png`` (255 on the object,
    0 elsewhere) and ``output/masks_<k>/<stem>.png`` lined up with ``images_<k>/`` pixel for pixel; the first's path."""
    name = mask_name(image_name)
    written = save_image(Image.fromarray(mask.astype(np.uint8) * 255), output / "masks" / name)
    for factor in downscales:
        save_image(Image.fromarray(downscale_mask(torch.from_numpy(mask), factor).numpy().astype(np.uint8) * 255), output / f"masks_{factor}" / name)
    return written
