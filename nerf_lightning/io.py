"""Writing run outputs so that a crash never leaves a half-written file: temporary file, then rename."""

from __future__ import annotations

import json
import os
import tempfile
from pathlib import Path
from typing import Any

import imageio.v3 as iio
import numpy as np
import torch


def _current_umask() -> int:
    mask = os.umask(0)
    os.umask(mask)
    return mask


_UMASK = _current_umask()


def write_atomic(path: str | Path, data: bytes) -> Path:
    """Write ``data`` to ``path`` through a temporary file in the same folder and a rename."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    handle, temporary = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.", suffix=".tmp")
    try:
        with os.fdopen(handle, "wb") as file:
            file.write(data)
        os.chmod(temporary, 0o666 & ~_UMASK)  # mkstemp makes the file private; the result gets the usual permissions
        os.replace(temporary, path)
    except BaseException:
        Path(temporary).unlink(missing_ok=True)
        raise
    return path


def write_json(path: str | Path, payload: Any) -> Path:
    return write_atomic(path, (json.dumps(payload, indent=2, sort_keys=True) + "\n").encode())


def to_uint8(image: torch.Tensor) -> np.ndarray:
    """(H, W, 3) or (H, W) floats in [0, 1] -> uint8 array, rounded; uint8 passes through."""
    if image.dtype == torch.uint8:
        return image.detach().cpu().numpy()
    return (image.detach().float().clamp(0, 1) * 255.0 + 0.5).to(torch.uint8).cpu().numpy()


def write_png(path: str | Path, image: torch.Tensor) -> Path:
    """Save (H, W, 3) or (H, W) floats in [0, 1] as an 8-bit PNG."""
    return write_atomic(path, iio.imwrite("<bytes>", to_uint8(image), extension=".png"))
