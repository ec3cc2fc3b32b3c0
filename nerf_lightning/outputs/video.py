"""Writing frames as PNG files, a GIF and (with the optional imageio-ffmpeg) an MP4."""

from __future__ import annotations

import logging
from collections.abc import Sequence
from pathlib import Path

import imageio.v3 as iio
import numpy as np

from nerf_lightning.io import write_atomic

log = logging.getLogger(__name__)


def write_gif(path: str | Path, frames: Sequence[np.ndarray], fps: float = 20.0) -> Path:
    """uint8 frames (H, W, 3) or (H, W) -> a looping GIF."""
    return write_atomic(path, iio.imwrite("<bytes>", np.stack(frames), extension=".gif", duration=1000.0 / fps, loop=0))


def write_mp4(path: str | Path, frames: Sequence[np.ndarray], fps: float = 20.0) -> Path | None:
    """An H.264 MP4 when imageio-ffmpeg is installed (the ``video`` extra); otherwise None, with a note."""
    try:
        import imageio_ffmpeg  # noqa: F401
    except ImportError:
        log.info('no MP4 for %s: install the video extra (pip install -e ".[video]") for imageio-ffmpeg', path)
        return None
    stack = np.stack([frame if frame.ndim == 3 else np.repeat(frame[..., None], 3, axis=-1) for frame in frames])
    # H.264 wants even sizes
    stack = stack[:, : stack.shape[1] // 2 * 2, : stack.shape[2] // 2 * 2]
    return write_atomic(path, iio.imwrite("<bytes>", stack, extension=".mp4", fps=fps, codec="libx264", macro_block_size=1))
