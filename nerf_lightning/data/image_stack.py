"""The images of a split as one (N, H, W, 3) uint8 tensor (and its masks as one (N, H, W) bool tensor), held in
memory or memory-mapped from a cache file.

Loaders decode one image at a time into the stack, so loading holds one float image besides the uint8 stack, a
quarter of the float size. With ``cache`` (``data.scene.image_cache=<folder>``) the stack is a raw file in that
folder mapped into memory (:class:`numpy.memmap`): the operating system reads in the pixels a batch touches and
may drop them again under memory pressure, so a scene larger than memory still trains (rays are made per batch,
:func:`~nerf_lightning.geometry.rays.indexed_pixel_rays`), and processes on one machine (DDP ranks, the runs of
a sweep) share one copy. The file is written once, atomically (temporary file, then rename), and reused while
the image files (paths, sizes, modification times), the files they depend on and the loader's settings are the
same; other settings get files of their own. Delete the folder to reclaim the space, but never edit or cut
short a file a running process maps (the kernel would stop that process with a bus error); this module only
ever replaces whole files.
"""

from __future__ import annotations

import hashlib
import json
import os
import re
from collections.abc import Callable, Iterator, Sequence
from pathlib import Path
from typing import Any

import numpy as np
import torch

from nerf_lightning.errors import ensure_writable
from nerf_lightning.io import to_uint8, write_json

CACHE_VERSION = 1  # bump when what a loader stores changes


def as_float_rgb(images: torch.Tensor) -> torch.Tensor:
    """RGB of any shape (..., 3): uint8 0..255 -> float32 in [0, 1]; float passes through unchanged."""
    return images.to(torch.float32) / 255.0 if images.dtype == torch.uint8 else images


def _quantised(paths: Sequence[Path], decode: Callable[[Path], torch.Tensor]) -> Iterator[np.ndarray]:
    """decode(path) -> (H, W, 3) floats (or (H, W) bools) for each path in turn, as (H, W, 3) uint8 (or (H, W)
    bool), all of the first one's size."""
    first: tuple[int, ...] | None = None
    for path in paths:
        image = decode(path)
        if first is None:
            first = tuple(image.shape)
        elif tuple(image.shape) != first:
            raise ValueError(f"{path} is {image.shape[1]}x{image.shape[0]} but {paths[0].name} is {first[1]}x{first[0]}: "
                             "all images of a split must have one size")
        yield image.numpy() if image.dtype == torch.bool else to_uint8(image)


def _stamp(path: Path) -> list[Any]:
    if not path.is_file():
        raise FileNotFoundError(f"file not found: {path}")
    stat = path.stat()
    return [str(path.resolve()), stat.st_size, stat.st_mtime_ns]


def cache_name(label: str, paths: Sequence[Path], recipe: dict[str, Any], depends_on: Sequence[Path] = ()) -> str:
    """``<label>-<hash>``: the hash of the files' paths, sizes and modification times and of ``recipe``."""
    identity = {"version": CACHE_VERSION, "recipe": recipe, "files": [_stamp(Path(p)) for p in [*paths, *depends_on]]}
    digest = hashlib.sha256(json.dumps(identity, sort_keys=True, default=str).encode()).hexdigest()[:20]
    return f"{re.sub(r'[^A-Za-z0-9_.-]+', '_', label)}-{digest}"


def _map(path: Path, shape: tuple[int, ...]) -> torch.Tensor:
    """The raw file as a (N, H, W, 3) uint8 tensor (or (N, H, W) bool: masks, a byte a pixel) over a copy-on-write
    mapping: pages are read on demand and shared."""
    return torch.from_numpy(np.memmap(path, dtype=np.uint8 if len(shape) == 4 else np.bool_, mode="c", shape=shape))


def _cached_shape(data: Path, meta: Path) -> tuple[int, ...] | None:
    """The stored shape where both files are there and agree; None otherwise (a miss: the stack is written again)."""
    try:
        shape = tuple(int(size) for size in json.loads(meta.read_text())["shape"])
        return shape if len(shape) in (3, 4) and data.stat().st_size == int(np.prod(shape)) else None
    except (OSError, ValueError, KeyError, TypeError):
        return None


def stack_images(
    paths: Sequence[Path],
    decode: Callable[[Path], torch.Tensor],
    cache: str | Path | None = None,
    label: str = "images",
    recipe: dict[str, Any] | None = None,
    depends_on: Sequence[Path] = (),
) -> torch.Tensor:
    """(N, H, W, 3) uint8 of ``decode(path)`` ((H, W, 3) floats in [0, 1]) for each of the N paths, rounded; or
    (N, H, W) bool where ``decode`` gives (H, W) bools (masks: :func:`~nerf_lightning.data.images.load_mask`).

    Args:
        paths: the image files, in the order of the views.
        decode: reads and prepares one image (composite, downscale, undistort) or mask; raises naming the file.
        cache: a folder: the stack is memory-mapped from a file there (written now, or reused); None keeps it in memory.
        label: the start of the cache file's name (the scene and split), for people looking in the folder.
        recipe: every setting ``decode`` depends on besides the files (downscale, background, ...).
        depends_on: other files ``decode`` reads (a json with the intrinsics it undistorts with).

    Raises ValueError naming the file whose size differs from the first's.
    """
    paths = [Path(p) for p in paths]
    if not paths:
        raise ValueError("stack_images: no image files given")
    if cache is None:
        stack = None
        for index, image in enumerate(_quantised(paths, decode)):
            if stack is None:
                stack = torch.empty((len(paths), *image.shape), dtype=torch.bool if image.dtype == np.bool_ else torch.uint8)
            stack[index] = torch.from_numpy(image)
        return stack

    folder = Path(cache).expanduser()
    name = cache_name(label, paths, recipe or {}, depends_on)
    data, meta = folder / f"{name}.u8", folder / f"{name}.json"
    shape = _cached_shape(data, meta)
    if shape is not None and shape[0] == len(paths):
        return _map(data, shape)
    ensure_writable(folder, "data.scene.image_cache")
    temporary = data.with_name(f".{data.name}.{os.getpid()}.tmp")
    try:
        with open(temporary, "wb") as file:  # plain writes, not a writable mapping: a full disk is an OSError, not a crash
            for image in _quantised(paths, decode):
                file.write(image.tobytes())
                shape = (len(paths), *image.shape)
        os.replace(temporary, data)
    except BaseException:
        temporary.unlink(missing_ok=True)
        raise
    write_json(meta, {"shape": list(shape), "files": [p.name for p in paths], "recipe": recipe or {}, "version": CACHE_VERSION})
    return _map(data, shape)
