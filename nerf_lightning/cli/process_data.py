"""nerf-process-data: a folder of photos or a video posed with COLMAP (pycolmap, in-process) into a capture that
nerf-train reads (:func:`nerf_lightning.capture.process_capture`), and its report printed; with masks=<folder>,
a mask a photo, COLMAP matches the object alone and the masks are written beside the images."""

from __future__ import annotations

import hydra
from omegaconf import DictConfig

from nerf_lightning.cli.keys import check_process_data_keys
from nerf_lightning.errors import report_errors


def process(cfg: DictConfig) -> dict:
    check_process_data_keys(cfg)
    # imported here, not at the top: a wrong key is answered before torch and Lightning load (seconds)
    from nerf_lightning.capture import process_capture

    return process_capture(cfg.input, cfg.output, frames=cfg.frames, matcher=cfg.matcher, mapper=cfg.mapper, camera_model=cfg.camera_model,
                           single_camera=cfg.single_camera, max_size=cfg.max_size, max_features=cfg.max_features,
                           downscales=list(cfg.downscales), min_registered=cfg.min_registered, escalate=cfg.escalate, seed=cfg.seed,
                           masks=None if cfg.masks in (None, "") else str(cfg.masks), mask_object=str(cfg.mask_object),
                           min_mask_agreement=cfg.min_mask_agreement, check_poses=cfg.check_poses, progress=cfg.progress, verbose=cfg.verbose)


@hydra.main(version_base="1.3", config_path="pkg://nerf_lightning.conf", config_name="process_data")
@report_errors("nerf-process-data")
def main(cfg: DictConfig) -> None:
    result = process(cfg)  # first: its keys are checked before torch loads
    from nerf_lightning.capture import format_report

    print(format_report(result))


if __name__ == "__main__":
    main()
