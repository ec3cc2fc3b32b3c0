"""nerf-process-data: the user's own photos or video posed in-process through pycolmap, the result written as
nerfstudio's transforms.json; and the sparse points of a capture that has poses but no points, triangulated with the
poses held fixed (:mod:`~nerf_lightning.capture.triangulate`).

Its modules load when first asked for, so that the command's key check reads :mod:`~nerf_lightning.capture.choices`
without loading torch or pycolmap."""

from __future__ import annotations

from typing import TYPE_CHECKING

from nerf_lightning.lazy import lazy_attributes

_HOMES = {"compare_with_reference": "compare", "format_report": "report", "process_capture": "process"}

__all__ = sorted(_HOMES)

if TYPE_CHECKING:
    from nerf_lightning.capture.compare import compare_with_reference
    from nerf_lightning.capture.process import process_capture
    from nerf_lightning.capture.report import format_report


__getattr__ = lazy_attributes(__name__, _HOMES)
