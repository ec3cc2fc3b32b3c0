"""What ``nerf-export`` writes, by format, and what a model needs to be exported in it.

Each format names the capability it asks of the model (a protocol of :mod:`nerf_lightning.models.contract`) and
the writer; a model is exported in every format whose capability it has, and asked for another one, the command
names the formats it does have. A new export is one entry here.
"""

from __future__ import annotations

import logging
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from nerf_lightning.models.contract import HasDensity, HasGaussians, implements
from nerf_lightning.outputs.mesh import FORMATS as MESH_FORMATS
from nerf_lightning.outputs.mesh import mesh_model, write_mesh

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class ExportFormat:
    """One format: the capability it needs (``needs``, in words for messages), and ``write(model, options,
    output_dir) -> path``, where ``options`` are nerf-export's keys."""

    capability: type
    needs: str
    write: Callable[[Any, Mapping[str, Any], Path], Path]


def _mesh_writer(file_type: str) -> Callable[[Any, Mapping[str, Any], Path], Path]:
    def write(model: HasDensity, options: Mapping[str, Any], output_dir: Path) -> Path:
        mesh, info = mesh_model(model, options.get("bounds"), int(options.get("resolution", 128)), float(options.get("threshold", 10.0)),
                                options.get("keep", 100), options.get("frame", "capture"))
        path = write_mesh(output_dir / f"mesh.{file_type}", mesh)
        log.info("wrote %s: %d vertices, %d faces of %d kept (keep=%s; grid %d^3 over %s..%s, threshold %g, %s coordinates)", path,
                 info["vertices"], info["faces"], info["faces_before_keep"], info["keep"], int(options.get("resolution", 128)), *info["box"],
                 float(options.get("threshold", 10.0)), info["frame"])
        return path

    return write


def splats_in_frame(model: HasGaussians, frame: str) -> dict[str, Any]:
    """The model's Gaussians in the capture's coordinates (``frame=capture``: the loader's similarity undone, so the
    splats line up with the capture's own cameras and sparse points) or the scene's (``frame=scene``)."""
    import torch

    from nerf_lightning.splats.gaussians import transform_gaussians

    if frame not in ("capture", "scene"):
        raise ValueError(f"export frame must be capture or scene, got '{frame}'")
    parameters = model.gaussian_parameters()
    world_from_capture = getattr(getattr(model, "space", None), "world_from_capture", None)
    if frame == "capture" and world_from_capture is not None:  # on the CPU (Apple GPUs have no float64): both move there
        parameters = transform_gaussians(parameters, torch.linalg.inv(world_from_capture.cpu().double()))
    return parameters


def _write_splats(model: HasGaussians, options: Mapping[str, Any], output_dir: Path) -> Path:
    """The splat PLY, in the capture's or the scene's coordinates (:func:`splats_in_frame`)."""
    from nerf_lightning.splats.ply import write_splat_ply

    frame = options.get("frame", "capture")
    parameters = splats_in_frame(model, frame)
    path = write_splat_ply(output_dir / "splats.ply", **parameters)
    log.info("wrote %s: %d Gaussians (the 3DGS layout: SuperSplat and the web splat viewers open it), in the %s's coordinates",
             path, len(parameters["means"]), frame)
    return path


def _write_splats_spz(model: HasGaussians, options: Mapping[str, Any], output_dir: Path) -> Path:
    """The same Gaussians as the splat PLY, as Niantic's SPZ (:mod:`nerf_lightning.splats.spz`: 8-bit and 24-bit
    quantised, gzipped, turned from the PLY's RDF to SPZ's RUB)."""
    from nerf_lightning.splats.spz import SH1_BITS, SH_REST_BITS, write_splat_spz

    frame = options.get("frame", "capture")
    parameters = splats_in_frame(model, frame)
    # the header's flag: drawn with Mip-Splatting's opacity compensation, a viewer should draw it so too
    antialiased = bool(getattr(getattr(model, "rasterizer", None), "antialiased", False))
    path = write_splat_spz(output_dir / "splats.spz", **parameters, antialiased=antialiased, sh1_bits=int(options.get("sh1_bits", SH1_BITS)),
                           sh_rest_bits=int(options.get("sh_rest_bits", SH_REST_BITS)))
    log.info("wrote %s: %d Gaussians, %.1f MB (SPZ version 3: SuperSplat, Spark, Babylon.js and Niantic's loader read it), in the %s's "
             "coordinates turned to SPZ's RUB", path, len(parameters["means"]), path.stat().st_size / 1e6, frame)
    return path


# a name can have several exports, by what the model has: the first the model can do is written
EXPORT_FORMATS: dict[str, tuple[ExportFormat, ...]] = {
    file_type: (ExportFormat(HasDensity, "a density to mesh (marching cubes)", _mesh_writer(file_type)),) for file_type in MESH_FORMATS
}
EXPORT_FORMATS["ply"] = (ExportFormat(HasGaussians, "Gaussians (a splat PLY)", _write_splats), *EXPORT_FORMATS["ply"])
EXPORT_FORMATS["spz"] = (ExportFormat(HasGaussians, "Gaussians (a splat SPZ)", _write_splats_spz),)


def formats_of(model: Any) -> list[str]:
    """The formats ``model`` can be exported in."""
    return [name for name, entries in EXPORT_FORMATS.items() if any(implements(model, entry.capability) for entry in entries)]


def export_model(model: Any, file_format: str, output_dir: str | Path, options: Mapping[str, Any]) -> Path:
    """Write ``model`` in ``file_format`` into ``output_dir``; ValueError in one line for an unknown format or one
    the model cannot be exported in (naming those it can)."""
    entries = EXPORT_FORMATS.get(str(file_format))
    if entries is None:
        raise ValueError(f"format must be one of {', '.join(EXPORT_FORMATS)}, got '{file_format}'")
    entry = next((entry for entry in entries if implements(model, entry.capability)), None)
    if entry is None:
        have = formats_of(model)
        offer = f"it exports {', '.join(have)}" if have else "it has nothing nerf-export writes"
        needs = " or ".join(entry.needs for entry in entries)
        raise ValueError(f"format={file_format} needs {needs}; this checkpoint's model, {type(model).__name__}, has none: {offer}")
    return entry.write(model, options, Path(output_dir))
