"""nerf-viz-cameras: cameras, random rays and their samples of a scene, as a PNG or in the browser (viser)."""

from __future__ import annotations

import logging
import sys
import time
from pathlib import Path

import hydra
from hydra.utils import instantiate
from omegaconf import DictConfig

from nerf_lightning.cli.keys import check_viz_cameras_keys
from nerf_lightning.config import renamed_key_message
from nerf_lightning.errors import fail, report_errors

log = logging.getLogger(__name__)


def visualise(cfg: DictConfig) -> Path | object:
    check_viz_cameras_keys(cfg)
    # imported here, not at the top: a wrong key is answered before torch loads (seconds)
    from nerf_lightning.devices import resolve_device
    from nerf_lightning.viz.plot import plot_cameras_and_rays
    from nerf_lightning.viz.rays_sample import draw_rays

    resolve_device(cfg.device)  # validated like the other commands' key; a few dozen rays are drawn on the CPU
    datamodule = instantiate(cfg.data)
    datamodule.setup()
    scene = datamodule.scene
    all_rays = draw_rays(scene, cfg.viz.n_rays, cfg.viz.n_samples, seed=cfg.seed)
    one_camera = draw_rays(scene, cfg.viz.n_rays_one_camera, cfg.viz.n_samples, camera=cfg.viz.camera, seed=cfg.seed + 1)
    if cfg.viz.backend == "png":
        path = plot_cameras_and_rays(scene, all_rays, one_camera, cfg.viz.camera, Path(cfg.output_dir) / "cameras.png")
        log.info("wrote %s", path)
        return path
    if cfg.viz.backend == "viser":
        from nerf_lightning.viz.viser_view import serve_scene

        server = serve_scene(scene, all_rays, one_camera, cfg.viz.camera, host=cfg.viz.host, port=cfg.viz.port)
        log.info("viser is serving the scene at http://%s:%d (Ctrl-C to stop)", cfg.viz.host, cfg.viz.port)
        return server
    raise ValueError(f"viz.backend must be png or viser, got '{cfg.viz.backend}'")


@hydra.main(version_base="1.3", config_path="pkg://nerf_lightning.conf", config_name="viz")
@report_errors("nerf-viz-cameras")
def run(cfg: DictConfig) -> None:
    result = visualise(cfg)
    if cfg.viz.backend == "viser":
        try:
            while True:
                time.sleep(1.0)
        except KeyboardInterrupt:
            result.stop()


def main() -> None:
    message = renamed_key_message(sys.argv[1:])  # data=blender and the like, the choices of before 0.4
    if message:
        fail("nerf-viz-cameras", message)
    run()


if __name__ == "__main__":
    main()
