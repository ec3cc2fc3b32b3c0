"""nerf-export: a trained model in a file other programs open: a coloured mesh of a model with a density, by marching
cubes (PLY, OBJ or GLB), floaters dropped, in the capture's coordinates (:mod:`nerf_lightning.outputs.export` lists
the formats and what each needs of a model)."""

from __future__ import annotations

from pathlib import Path

import hydra
from omegaconf import DictConfig

import nerf_lightning.config  # noqa: F401 (registers ${run_dir_of:...}, which the config's output_dir uses)
from nerf_lightning.cli.keys import check_export_keys
from nerf_lightning.errors import ensure_writable, report_errors


def export(cfg: DictConfig) -> Path:
    check_export_keys(cfg)
    # imported here, not at the top: a wrong key is answered before torch and Lightning load (seconds)
    from nerf_lightning.checkpoints import load_model
    from nerf_lightning.outputs.export import export_model

    model, _ = load_model(cfg.ckpt_path, cfg.device, trust=cfg.trust_checkpoint)
    output_dir = ensure_writable(cfg.output_dir, "output_dir")
    return export_model(model, cfg.format, output_dir, cfg)


@hydra.main(version_base="1.3", config_path="pkg://nerf_lightning.conf", config_name="export")
@report_errors("nerf-export")
def main(cfg: DictConfig) -> None:
    export(cfg)


if __name__ == "__main__":
    main()
