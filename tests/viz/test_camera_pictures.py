"""Pictures of cameras and rays: nerf-viz-cameras, and the viser view in a headless browser."""

import imageio.v3 as iio
import numpy as np

from nerf_lightning.geometry import pinhole_camera
from nerf_lightning.viz.rays_sample import draw_rays
from tests.conftest import run_cli
from tests.viz.conftest import free_port, needs_browser, wait_for


def test_one_cameras_rays_stay_inside_its_frustum(procedural_scene):
    sample = draw_rays(procedural_scene, n_rays=200, n_samples=16, camera=5, seed=0)
    train = procedural_scene.train
    camera = pinhole_camera(train.K[5:6], train.c2w[5:6], train.height, train.width)
    uv = camera.project(sample.points.reshape(1, -1, 3))[0]
    assert (uv >= 0).all() and (uv[:, 0] <= train.width).all() and (uv[:, 1] <= train.height).all()
    depth = (sample.points - sample.rays_o[:, None]).norm(dim=-1)
    assert (depth >= procedural_scene.near - 1e-5).all() and (depth <= procedural_scene.far + 1e-5).all()


def test_nerf_viz_cameras_writes_the_picture(tmp_path, scene_cache, monkeypatch):
    monkeypatch.setenv("NERF_LIGHTNING_CACHE", str(scene_cache))
    run_cli("viz_cameras", f"output_dir={tmp_path / 'viz'}", cwd=tmp_path)
    picture = iio.imread(tmp_path / "viz" / "cameras.png")
    assert picture.shape[0] > 500 and picture.shape[1] > 1000
    # drawn, not blank: red rays, blue frusta and green one-camera rays are all there
    rgb = picture[..., :3].astype(int)
    red = ((rgb[..., 0] > 180) & (rgb[..., 1] < 120) & (rgb[..., 2] < 120)).sum()
    green = ((rgb[..., 1] > 120) & (rgb[..., 0] < 120) & (rgb[..., 2] < 120)).sum()
    blue = ((rgb[..., 2] > 150) & (rgb[..., 0] < 100)).sum()
    assert red > 200 and green > 100 and blue > 200


@needs_browser
def test_viser_view_reaches_a_headless_browser(procedural_scene, browser, tmp_path):
    from nerf_lightning.viz.viser_view import serve_scene

    all_rays = draw_rays(procedural_scene, 32, 8, seed=0)
    one = draw_rays(procedural_scene, 16, 8, camera=0, seed=1)
    server = serve_scene(procedural_scene, all_rays, one, 0, port=free_port())
    try:
        page = browser.new_page(viewport={"width": 800, "height": 600})
        page.goto(f"http://127.0.0.1:{server.get_port()}/")
        wait_for(lambda: len(server.get_clients()) > 0, what="the page to connect to the viser server")

        def frustum_blue() -> int:
            # the scene arrived: the frustums' own blue (40, 90, 200), which viser's interface does not use, is drawn
            screenshot = iio.imread(page.screenshot(), extension=".png")[..., :3].astype(int)
            return int((np.abs(screenshot - np.array([40, 90, 200])).max(axis=-1) < 40).sum())

        wait_for(lambda: frustum_blue() > 500, what="the camera frustums to be drawn")
    finally:
        server.stop()
