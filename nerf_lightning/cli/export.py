"""nerf-export: a coloured mesh of a radiance field by marching cubes on its density (PLY, OBJ or GLB), floaters
dropped, in the capture's coordinates (:func:`nerf_lightning.mesh.mesh_radiance_field`)."""

from __future__ import annotations

import logging
from pathlib import Path

import hydra
from omegaconf import DictConfig

import nerf_lightning.config  # noqa: F401 (registers ${run_dir_of:...}, which the config's output_dir uses)
from nerf_lightning.errors import ensure_writable, report_errors

log = logging.getLogger(__name__)


def export(cfg: DictConfig) -> Path:
    # imported here, not at the top: a wrong key is answered before torch and Lightning load (seconds)
    from nerf_lightning.checkpoints import load_model
    from nerf_lightning.mesh import FORMATS, mesh_radiance_field, write_mesh

    if cfg.format not in FORMATS:
        raise ValueError(f"export format must be one of {', '.join(FORMATS)}, got '{cfg.format}'")
    model, _ = load_model(cfg.ckpt_path, cfg.device, kind="radiance_field", command="nerf-export")
    output_dir = ensure_writable(cfg.output_dir, "output_dir")
    mesh, info = mesh_radiance_field(model, cfg.bounds, cfg.resolution, cfg.threshold, cfg.keep, cfg.frame)
    path = write_mesh(output_dir / f"mesh.{cfg.format}", mesh)
    log.info("wrote %s: %d vertices, %d faces of %d kept (keep=%s; grid %d^3 over %s..%s, threshold %g, %s coordinates)", path,
             info["vertices"], info["faces"], info["faces_before_keep"], info["keep"], cfg.resolution, *info["box"], cfg.threshold, cfg.frame)
    return path


@hydra.main(version_base="1.3", config_path="pkg://nerf_lightning.conf", config_name="export")
@report_errors("nerf-export")
def main(cfg: DictConfig) -> None:
    export(cfg)


if __name__ == "__main__":
    main()
