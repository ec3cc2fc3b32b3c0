"""What ``nerf-process-data`` writes beside its images: the sparse points as a PLY, and everything staged moved into
the output folder at the end, transforms.json last, replacing what an earlier run wrote there.
"""

from __future__ import annotations

import os
import re
from pathlib import Path

import numpy as np
import trimesh

from nerf_lightning.io import write_atomic


def write_points_ply(path: Path, positions: np.ndarray, colours: np.ndarray) -> Path:
    """(P, 3) positions and (P, 3) uint8 RGB colours as a binary PLY point cloud (trimesh)."""
    cloud = trimesh.PointCloud(positions, colors=np.concatenate([colours, np.full((len(colours), 1), 255, np.uint8)], axis=1))
    return write_atomic(path, cloud.export(file_type="ply"))


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
