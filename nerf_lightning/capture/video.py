"""Frames of a video for structure from motion: ``count`` of them spread over the clip, each the sharpest of its
stretch by the variance of the Laplacian (a blurred frame has weak second derivatives everywhere).

Frames are decoded through imageio's ffmpeg plugin (the ``video`` extra, imageio-ffmpeg, which ships ffmpeg).
"""

from __future__ import annotations

import itertools
import logging
from collections.abc import Callable, Iterator
from pathlib import Path

import numpy as np

from nerf_lightning.errors import MissingExtraError

log = logging.getLogger(__name__)

VIDEO_SUFFIXES = (".mp4", ".mov", ".m4v", ".avi", ".mkv", ".webm", ".mpg", ".mpeg", ".3gp")
VIDEO_EXTRA = 'pip install -c constraints-cpu.txt -e ".[video]"'


def is_video(path: Path) -> bool:
    return path.is_file() and path.suffix.lower() in VIDEO_SUFFIXES


def laplacian_variance(image: np.ndarray) -> float:
    """Sharpness of an (H, W, 3) or (H, W) image: the variance of its grey levels' 4-neighbour Laplacian.

    Images over 1000 pixels on their long side are first averaged over k x k blocks down to about 720, so the measure
    sees detail at the scale feature matching does and costs a few milliseconds.
    """
    grey = image.astype(np.float32)
    if grey.ndim == 3:
        grey = grey[..., :3] @ np.array([0.299, 0.587, 0.114], dtype=np.float32)
    factor = max(1, max(grey.shape) // 720) if max(grey.shape) > 1000 else 1
    if factor > 1:
        height, width = grey.shape[0] // factor, grey.shape[1] // factor
        grey = grey[: height * factor, : width * factor].reshape(height, factor, width, factor).mean((1, 3))
    laplacian = grey[:-2, 1:-1] + grey[2:, 1:-1] + grey[1:-1, :-2] + grey[1:-1, 2:] - 4.0 * grey[1:-1, 1:-1]
    return float(laplacian.var())


def frame_count(path: Path) -> int:
    """The number of frames in a video (ffmpeg counts the packets without decoding them)."""
    import imageio_ffmpeg

    frames, _ = imageio_ffmpeg.count_frames_and_secs(str(path))
    return int(frames)


def read_frames(path: Path) -> Iterator[np.ndarray]:
    """Every frame of a video, (H, W, 3) uint8, in order."""
    import imageio.v3 as iio

    yield from iio.imiter(path, plugin="FFMPEG")


def stretches(total: int, count: int) -> np.ndarray:
    """(total,) the stretch each of ``total`` frames belongs to when cut into ``count`` equal stretches
    (every frame its own when there are no more than ``count``)."""
    count = min(count, total)
    return np.arange(total) * count // total


def pick_sharp_frames(path: Path, count: int, write: Callable[[np.ndarray, int], None],
                      progress: Callable[[int], None] | None = None) -> list[dict]:
    """The sharpest frame of each of ``count`` equal stretches of the video ``path``, handed to ``write(frame, i)``
    (i = 0, 1, ... in time order) as soon as its stretch has been read, so one frame is held at a time.

    Returns, for each frame written, its index in the video and its sharpness. ``progress(n)`` is told each
    decoded frame. Raises ValueError naming the file when ffmpeg cannot read it or it has no frames, and
    MissingExtraError naming the ``video`` extra without imageio-ffmpeg.
    """
    try:
        import imageio_ffmpeg  # noqa: F401
    except ImportError:
        raise MissingExtraError(f"reading the video {path} needs imageio-ffmpeg, the video extra: {VIDEO_EXTRA}") from None
    if count < 1:
        raise ValueError(f"frames must be at least 1, got {count}")
    try:
        total = frame_count(path)
    except Exception as error:  # ffmpeg's failures surface as RuntimeError or OSError with its output
        raise ValueError(f"could not read the video {path}: {str(error).strip().splitlines()[-1] if str(error).strip() else error}") from error
    if total < 1:
        raise ValueError(f"the video {path} has no frames")
    stretch_of = stretches(total, count)

    picked: list[dict] = []
    best: tuple[float, int, np.ndarray] | None = None
    current = 0

    def flush() -> None:
        sharpness, index, frame = best
        write(frame, len(picked))
        picked.append({"frame": index, "sharpness": round(sharpness, 2)})

    frames = read_frames(path)
    for index in itertools.count():
        try:
            frame = next(frames)
        except StopIteration:
            break
        except Exception as error:  # a truncated or corrupt stream
            if best is None and not picked:
                raise ValueError(f"could not read the video {path}: {error}") from error
            log.warning("%s: reading stopped early at frame %d (%s); keeping the frames read so far", path, index, error)
            break
        stretch = int(stretch_of[min(index, total - 1)])  # ffmpeg may decode a frame or two more than it counted
        if stretch != current and best is not None:
            flush()
            best = None
        current = stretch
        sharpness = laplacian_variance(frame)
        if best is None or sharpness > best[0]:
            best = (sharpness, index, frame)
        if progress is not None:
            progress(1)
    if best is not None:
        flush()
    if not picked:
        raise ValueError(f"the video {path} has no frames that could be decoded")
    return picked
