"""A capture's photos, made ready for structure from motion and for training: turned upright by their EXIF
orientation, written to ``images/`` at full resolution and to ``images_<k>/`` downscaled k times (nerfstudio's layout).

A phone stores a portrait photo as landscape pixels plus an EXIF tag saying how to turn it; COLMAP and this
project's loaders read the pixels as stored, so the pixels themselves are turned here, once.
"""

from __future__ import annotations

import io
import re
import shutil
from collections.abc import Iterable
from pathlib import Path

from PIL import Image, ImageOps

from nerf_lightning.io import write_atomic

# read by Pillow; HEIC/HEIF (iPhones) is listed so that such files are named as unreadable rather than silently left out
IMAGE_SUFFIXES = (".jpg", ".jpeg", ".png", ".tif", ".tiff", ".bmp", ".webp", ".heic", ".heif")
EXIF_ORIENTATION = 0x0112
JPEG_QUALITY = 95


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
