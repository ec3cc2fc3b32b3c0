"""nerf-view: a trained model of a scene in the browser (extra ``viz``), rendered from the browser's camera
(:class:`~nerf_lightning.viz.viewer.FieldViewer`); Gaussian splats are drawn by the browser itself unless the page
asks for rendered frames (:mod:`nerf_lightning.viz.splats`)."""

from __future__ import annotations

import logging
from typing import TYPE_CHECKING

import hydra
from omegaconf import DictConfig

import nerf_lightning.config  # noqa: F401 (registers ${run_dir_of:...}, which the config's output_dir uses)
from nerf_lightning.cli.keys import check_view_keys
from nerf_lightning.errors import report_errors

if TYPE_CHECKING:
    from nerf_lightning.viz.viewer import FieldViewer

log = logging.getLogger(__name__)


def view(cfg: DictConfig) -> FieldViewer:
    """Start the viewer of ``cfg.ckpt_path`` on ``cfg.host``:``cfg.port`` (the caller runs ``serve_forever``)."""
    check_view_keys(cfg)
    # imported here, not at the top: a wrong key is answered before torch loads (seconds)
    from nerf_lightning.checkpoints import load_model, load_run_data
    from nerf_lightning.models.contract import RendersCamera, require
    from nerf_lightning.viz.viewer import FieldViewer
    from nerf_lightning.viz.viser_view import start_server

    server = start_server(cfg.host, cfg.port)  # before loading anything: a missing extra or a taken port fails at once
    try:
        model, info = load_model(cfg.ckpt_path, cfg.device, trust=cfg.trust_checkpoint)
        require(model, RendersCamera, "nerf-view", "a model that renders a camera")
        datamodule = load_run_data(info["config"], model)
        viewer = FieldViewer(server, model, datamodule.scene.train, datamodule.render_views, cfg.output_dir,
                             moving_frame_s=cfg.view.moving_frame_s, max_resolution=cfg.view.max_resolution,
                             max_splats=cfg.view.max_splats)
    except BaseException:
        server.stop()
        raise
    log.info("nerf-view: open http://%s:%d in a browser (Ctrl-C to stop)", cfg.host, cfg.port)
    return viewer


@hydra.main(version_base="1.3", config_path="pkg://nerf_lightning.conf", config_name="view")
@report_errors("nerf-view")
def main(cfg: DictConfig) -> None:
    viewer = view(cfg)
    try:
        viewer.serve_forever()
    except KeyboardInterrupt:
        pass
    finally:
        viewer.server.stop()


if __name__ == "__main__":
    main()
