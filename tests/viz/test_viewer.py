"""nerf-view and nerf-train viewer=live: the scheduler, the page and the callback without a browser, then the page in
headless Debian chromium (driven by Playwright), as a user would use it."""

from __future__ import annotations

import importlib.util
import json
import math
import os
import re
import signal
import socket
import subprocess
import sys
import time
import urllib.request
from pathlib import Path
from types import SimpleNamespace

import kornia
import numpy as np
import pytest
import torch

from nerf_lightning.config import compose_config, renamed_key_message
from nerf_lightning.geometry.space import SceneSpace
from nerf_lightning.metrics import mse_to_psnr
from nerf_lightning.models.contract import Overlay
from nerf_lightning.viz.scheduler import BrowserCamera, RenderScheduler, browser_camera, progressive_heights
from nerf_lightning.viz.viser_view import check_port
from tests.viz.conftest import free_port, needs_browser, open_page, wait_for


# a short run of the fast preset: 150 steps, a 32^3 occupancy grid
RUN = ["experiment=fast", "trainer.max_steps=150", "model.sampler.grid.resolution=32", "data.val_every=150",
       "trainer.enable_progress_bar=false", "trainer.enable_model_summary=false"]


@pytest.fixture(scope="module")
def trained(tmp_path_factory, scene_cache):
    """A trained checkpoint of the fast preset on the procedural scene and its loaded model."""
    from nerf_lightning.checkpoints import load_model
    from nerf_lightning.training import train

    run_dir = tmp_path_factory.mktemp("viewer_run")
    with pytest.MonkeyPatch.context() as patch:
        patch.setenv("NERF_LIGHTNING_CACHE", str(scene_cache))
        metrics = train(compose_config([*RUN, f"paths.output_dir={run_dir}"]))
        ckpt = run_dir / "checkpoints" / "last.ckpt"
        model, info = load_model(ckpt, "cpu")
        yield {"ckpt": ckpt, "model": model, "config": info["config"], "psnr": metrics["val/psnr"], "run_dir": run_dir}


# -- without a browser --------------------------------------------------------------------------------------------


def test_progressive_heights_double_up_to_the_largest():
    heights = progressive_heights(rays_per_second=100_000, moving_frame_s=0.25, aspect=4 / 3, max_height=600)
    assert heights[0] * heights[0] * 4 / 3 <= 100_000 * 0.25 * 1.01  # the first frame fits the moving budget
    assert heights[-1] == 600
    assert all(b == 2 * a for a, b in zip(heights[:-2], heights[1:-1])) and heights[-1] > heights[-2]
    assert progressive_heights(1e9, 0.25, 1.0, 300) == [300]  # a fast device renders the largest at once
    assert progressive_heights(10, 0.25, 1.0, 300)[0] == 24  # never below a readable size


def test_browser_camera_reproduces_a_training_camera(procedural_scene):
    """A browser camera placed where training view 3 is (viser: orientation and position of an OpenCV camera,
    vertical field of view) gives that view's K and c2w."""
    train = procedural_scene.train
    c2w = train.c2w[3]
    wxyz = kornia.geometry.conversions.rotation_matrix_to_quaternion(c2w[:3, :3].contiguous()).numpy()
    fov_y = 2.0 * math.atan(0.5 * train.height / float(train.K[3, 1, 1]))
    K, got, height, width = browser_camera(wxyz, c2w[:3, 3].numpy(), fov_y, train.width / train.height, train.height)
    assert (height, width) == (train.height, train.width)
    assert torch.allclose(got, c2w, atol=1e-5)
    assert torch.allclose(K, train.K[3], atol=1e-3)


def test_a_frame_from_a_training_camera_looks_like_its_image(trained, procedural_scene):
    model, train = trained["model"], procedural_scene.train
    frame = model.render_view(train.K[3], train.c2w[3], train.height, train.width)
    target = train.images[3].float() / 255.0
    assert float(mse_to_psnr(torch.mean((frame["rgb"].cpu() - target) ** 2))) > 15.0
    assert model.render_view(train.K[3], train.c2w[3], train.height, train.width, abort=lambda: True) is None


def test_scene_box_and_occupied_cells_in_the_world(trained):
    model = trained["model"]
    assert model.overlay_names() == {"box": "Scene box", "occupied_cells": "Occupied cells"}
    box = model.overlay("box")
    assert box.kind == "lines" and box.points.shape == (12, 2, 3) and np.allclose(np.abs(box.points), 1.3)  # the fast preset's field box
    cells = model.overlay("occupied_cells")
    assert cells.kind == "points" and 0 < len(cells.points) < 32**3 and cells.size == pytest.approx(2.6 / 32)
    assert (np.abs(cells.points) <= 1.3).all()


def test_a_taken_port_is_named(tmp_path, procedural_scene):
    with socket.socket() as holder:
        holder.bind(("127.0.0.1", 0))
        holder.listen()
        port = holder.getsockname()[1]
        with pytest.raises(ValueError, match=f"port {port} on 127.0.0.1 is taken.*callbacks.viewer.port=<port>"):
            check_port("127.0.0.1", port, "callbacks.viewer.port")
        if importlib.util.find_spec("viser") is not None:  # nerf-viz-cameras viz.backend=viser starts its server alike
            from nerf_lightning.viz.viser_view import serve_scene

            with pytest.raises(ValueError, match=f"port {port} on 127.0.0.1 is taken.*viz.port=<port>"):
                serve_scene(procedural_scene, None, None, 0, port=port)
        result = subprocess.run([sys.executable, "-m", "nerf_lightning.cli.view", "ckpt_path=any.ckpt", f"port={port}"],
                                cwd=tmp_path, capture_output=True, text=True, timeout=120)
    assert result.returncode == 2
    assert result.stderr.strip().splitlines()[-1] == (f"nerf-view: error: port {port} on 127.0.0.1 is taken by another program "
                                                      "(another viewer?): choose another with port=<port>")


def test_without_the_extra_the_commands_say_how_to_install_it(tmp_path):
    fake = tmp_path / "no_viser"
    (fake / "viser").mkdir(parents=True)
    (fake / "viser" / "__init__.py").write_text("raise ImportError('No module named viser')\n")
    env = dict(os.environ, PYTHONPATH=f"{fake}{os.pathsep}{os.environ.get('PYTHONPATH', '')}")
    for module, args in (("view", ["ckpt_path=any.ckpt"]), ("train", ["experiment=fast", "viewer=live", f"paths.output_dir={tmp_path / 'run'}"])):
        result = subprocess.run([sys.executable, "-m", f"nerf_lightning.cli.{module}", *args], cwd=tmp_path, env=env,
                                capture_output=True, text=True, timeout=120)
        assert result.returncode == 2, result.stderr
        assert 'needs viser, an optional extra: pip install -e ".[viz]"' in result.stderr.strip().splitlines()[-1]



@pytest.mark.skipif(importlib.util.find_spec("viser") is None, reason="viser (the viz extra) is not installed")
def test_nerf_view_serves_its_page_until_ctrl_c(trained, scene_cache, tmp_path):
    """The installed nerf-view on a trained checkpoint: it says where to look, that address serves the viewer's page,
    and Ctrl-C stops it cleanly."""
    port = free_port()
    env = dict(os.environ, NERF_LIGHTNING_CACHE=str(scene_cache), PYTHONUNBUFFERED="1")
    log_path = tmp_path / "view.log"
    command = [str(Path(sys.executable).parent / "nerf-view"), f"ckpt_path={trained['ckpt']}", f"port={port}", "device=cpu",
               f"output_dir={tmp_path / 'renders'}"]
    with open(log_path, "w") as log:
        # a shell's background job (CI run with `&`) ignores SIGINT, and its children inherit that: give the command Ctrl-C back
        process = subprocess.Popen(command, cwd=tmp_path, env=env, stdout=log, stderr=subprocess.STDOUT,
                                   preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL))
        try:
            wait_for(lambda: "in a browser" in log_path.read_text() or process.poll() is not None, seconds=120, what="nerf-view to start")
            assert process.poll() is None, log_path.read_text()[-3000:]
            assert f"open http://127.0.0.1:{port} in a browser" in log_path.read_text()
            with urllib.request.urlopen(f"http://127.0.0.1:{port}/", timeout=30) as response:
                assert response.status == 200 and b"<html" in response.read().lower()
            process.send_signal(signal.SIGINT)
            assert process.wait(timeout=60) == 0, log_path.read_text()[-3000:]
        finally:
            if process.poll() is None:
                process.kill()
    assert "Traceback" not in log_path.read_text()

# -- the scheduler alone ------------------------------------------------------------------------------------------


def _camera(x: float, aspect: float = 1.0, image_height: int = 400) -> BrowserCamera:
    return BrowserCamera(np.array([1.0, 0.0, 0.0, 0.0]), np.array([x, 0.0, -3.0]), math.radians(50.0), aspect, image_height)


def test_the_scheduler_renders_a_moved_camera_first_then_refines_it():
    now = [0.0]
    scheduler = RenderScheduler(moving_frame_s=0.25, max_resolution=256, refresh_s=2.0, clock=lambda: now[0])
    scheduler.rays_per_second = 4096 / 0.25  # the first frame of a square camera: 64 pixels high
    assert scheduler.next_job() is None  # nobody is connected
    for client in (1, 2):
        scheduler.connect(client)
        scheduler.camera_moved(client, _camera(float(client)))
    heights = scheduler.heights(_camera(0.0))
    assert heights == [64, 128, 256]

    def render(job):  # as the viewer does, at the rays per second measured so far
        K, c2w, height, width = job.pinhole()
        assert (height, width) == (job.height, job.height) and K[0, 2] == job.height / 2
        scheduler.rendered(job, width, seconds=height * width / scheduler.rays_per_second)

    # both cameras at the first height, then client 1 is refined, until client 2 moves: its first frame comes next
    first = []
    for _ in range(2):
        first.append(scheduler.next_job())
        render(first[-1])
    assert [(job.client_id, job.height, job.step) for job in first] == [(1, 64, 1), (2, 64, 1)]
    job = scheduler.next_job()
    assert (job.client_id, job.height, job.step, job.steps) == (1, 128, 2, 3)
    scheduler.camera_moved(2, _camera(5.0))
    assert not scheduler.is_stale(job)  # client 1's frame is still wanted
    render(job)
    moved = scheduler.next_job()
    assert (moved.client_id, moved.height, moved.step) == (2, 64, 1) and moved.camera.position[0] == 5.0
    scheduler.camera_moved(2, _camera(6.0))  # moved again while rendering: that frame is dropped
    assert scheduler.is_stale(moved)
    scheduler.rendered(moved, 64, 0.25)
    assert scheduler.next_job().camera.position[0] == 6.0

    # every camera refined to the last height, then nothing until a refresh is due
    while (job := scheduler.next_job()) is not None:
        render(job)
    assert scheduler.settled(1) and scheduler.settled(2)
    now[0] = 2.5
    refresh = scheduler.next_job()
    assert refresh.height == 64 and refresh.step == 1
    scheduler.disconnect(refresh.client_id)
    assert scheduler.is_stale(refresh)


def test_the_scheduler_refines_only_what_a_live_frame_affords():
    scheduler = RenderScheduler(moving_frame_s=0.1, max_resolution=512, max_frame_s=1.0)
    scheduler.rays_per_second = 40_000.0
    # 63 px while moving, then 126 (16k rays) fits a second at 40k rays/s; 252 (64k) and 512 do not
    assert scheduler.heights(_camera(0.0)) == [63, 126]
    assert scheduler.heights(_camera(0.0, image_height=100)) == [63, 100]  # never larger than the browser


# -- the page and the viewer with models that are not radiance fields ------------------------------------------------


class FakeModel:
    """Renders a grey picture through the contract and nothing else: no sampler, no field, no kind."""

    device = torch.device("cpu")
    space = SceneSpace(2.0, 6.0, (1.0, 1.0, 1.0))  # the contract's: the page writes camera paths through its world_from_capture

    def __init__(self):
        self.calls = []

    def render_view(self, K, c2w, height, width, abort=None):
        self.calls.append((tuple(K.shape), tuple(c2w.shape), height, width, abort is not None and not abort()))
        if abort is not None and abort():
            return None
        return {"rgb": torch.full((height, width, 3), 0.5), "depth": torch.ones(height, width),
                "accumulation": torch.ones(height, width)}


class FakeModelWithABox(FakeModel):
    def overlay_names(self):
        return {"box": "Scene box"}

    def overlay(self, name):
        corners = np.array([[0, 0, 0], [1, 0, 0]], dtype=np.float32)
        return Overlay("Scene box", "lines", np.stack([corners, corners + 1.0]), (200, 40, 160), 2.0)


@pytest.fixture
def server():
    viser = pytest.importorskip("viser")
    server = viser.ViserServer(host="127.0.0.1", port=free_port(), verbose=False)
    yield server
    server.stop()


def test_the_page_offers_exactly_the_overlays_the_model_names(server, procedural_scene):
    from nerf_lightning.viz.page import ViewerPage

    train = procedural_scene.train
    page = ViewerPage(server, FakeModelWithABox(), train, lambda path, frames: train, 256, lambda: None, lambda *request: None)
    assert list(page.overlay_boxes) == ["box"] and page.overlay_boxes["box"].label == "Scene box"
    page.overlay_boxes["box"].value = True
    page.draw_overlay("box")
    assert list(page.overlay_handles) == ["box"]
    page.overlay_boxes["box"].value = False
    page.draw_overlay("box")
    assert page.overlay_handles == {}
    assert len(page.frustums) == len(train)

    none = ViewerPage(server, FakeModel(), train, lambda path, frames: train, 256, lambda: None, lambda *request: None)
    assert none.overlay_boxes == {}
    none.redraw_overlays()  # nothing to draw, nothing asked of the model


def test_the_viewer_renders_through_render_view_and_drops_a_moved_frame(server, procedural_scene, tmp_path):
    from nerf_lightning.viz.viewer import FieldViewer

    train, model = procedural_scene.train, FakeModel()
    viewer = FieldViewer(server, model, train, lambda path, frames: train, tmp_path, moving_frame_s=0.25, max_resolution=64)
    viewer.scheduler.connect(7)  # a browser, as the page reports it
    viewer.scheduler.camera_moved(7, _camera(0.0, aspect=4 / 3))
    assert viewer.render_next() is not None and viewer.frames_rendered == 1
    height = model.calls[0][2]
    assert model.calls[0] == ((3, 3), (4, 4), height, round(height * 4 / 3), True)
    model.render_view = lambda K, c2w, height, width, abort=None: (viewer.scheduler.camera_moved(7, _camera(1.0)), abort())[1] and None
    viewer.render_next()  # the camera moves during the render: the frame is dropped, not counted
    assert viewer.frames_rendered == 1 and viewer.scheduler.next_job().camera.position[0] == 1.0


# -- the live view during training --------------------------------------------------------------------------------


def test_viewer_live_composes_into_the_callbacks_and_the_old_keys_name_the_new_ones(tmp_path):
    cfg = compose_config(["experiment=fast", "viewer=live", "callbacks.viewer.port=9123", f"paths.output_dir={tmp_path}"])
    viewer = cfg.callbacks.viewer
    assert viewer._target_ == "nerf_lightning.viz.live.LiveViewer"
    assert (viewer.host, viewer.port, viewer.time_share, viewer.output_dir) == ("127.0.0.1", 9123, 0.1, str(tmp_path))
    assert {"best_checkpoint", "last_checkpoint", "snapshots"} <= set(cfg.callbacks)  # added to the others
    assert "viewer" not in compose_config(["experiment=fast", f"paths.output_dir={tmp_path}"]).callbacks
    for old, new in (("viewer_port=9000", "callbacks.viewer.port"), ("viewer_host=0.0.0.0", "callbacks.viewer.host"),
                     ("viewer_time_share=0.2", "callbacks.viewer.time_share")):
        message = renamed_key_message([old])
        assert "when the live viewer became a callback" in message and message.endswith(f"use {new} (with viewer=live)")
    assert "use viewer=live for the live view" in renamed_key_message(["viewer=true"])
    assert renamed_key_message(["viewer=live"]) is None


def test_nerf_train_viewer_true_names_its_successor_in_one_line(tmp_path):
    import subprocess
    import sys

    result = subprocess.run([sys.executable, "-m", "nerf_lightning.cli.train", "experiment=fast", "viewer=true"], cwd=tmp_path,
                            capture_output=True, text=True, timeout=120)
    assert result.returncode == 2
    assert result.stderr.strip().splitlines() == ["nerf-train: error: 'viewer=true' was replaced in nerf-lightning 0.3, when the live "
                                                   "viewer became a callback (see CHANGELOG.md): use viewer=live for the live view, or "
                                                   "leave viewer out for none"]


def test_the_live_viewer_refuses_a_model_that_renders_no_camera(tmp_path):
    pytest.importorskip("viser")
    from types import SimpleNamespace

    from nerf_lightning.viz.live import LiveViewer
    from nerf_lightning.training import train

    callback = LiveViewer(port=free_port(), output_dir=tmp_path)
    with pytest.raises(ValueError) as refused:
        callback.setup(SimpleNamespace(is_global_zero=True), torch.nn.Linear(1, 1), "fit")
    assert str(refused.value) == ("viewer=live shows a model that renders a camera; this run trains a Linear, which renders none: "
                                  "leave viewer out, or train a radiance field (experiment=fast, ...)")
    assert callback.server is None
    with pytest.raises(ValueError, match="^viewer=live shows a model that renders a camera; this run trains a ImageFieldModule"):
        train(compose_config(["viewer=live", f"callbacks.viewer.port={free_port()}", "trainer.max_steps=1",
                              f"paths.output_dir={tmp_path / 'image'}"]))


class _FakeViewer:
    frames_rendered, path_requested = 0, False

    def __init__(self, render_next):
        self.render_next = render_next
        self.page = SimpleNamespace(redraw_overlays=lambda: None)
        self.shown = ""

    def show_training(self, text):
        self.shown = text


def _live_viewer(tmp_path, viewer, stopped=None):
    from nerf_lightning.viz.live import LiveViewer

    callback = LiveViewer(port=free_port(), output_dir=tmp_path)
    callback.viewer = viewer
    callback.server = SimpleNamespace(get_clients=lambda: {1: object()}, stop=lambda: stopped.append(True) if stopped is not None else None)
    callback._started = time.perf_counter() - 100.0
    return callback


def test_an_error_in_the_live_view_is_reported_once_and_training_goes_on(caplog, tmp_path):
    pytest.importorskip("viser")

    def broken():
        raise RuntimeError("the socket went away")

    stopped = []
    callback = _live_viewer(tmp_path, _FakeViewer(broken), stopped)
    module, trainer = torch.nn.Linear(1, 1), SimpleNamespace(callback_metrics={}, global_step=7)
    module.train()
    with caplog.at_level("WARNING"):
        for _ in range(3):  # the step after the error and those after it: no exception, one warning
            callback.on_train_batch_end(trainer, module, None, None, 0)
    warnings = [r for r in caplog.records if "live viewer stopped" in r.getMessage()]
    assert len(warnings) == 1 and "RuntimeError: the socket went away" in warnings[0].getMessage()
    assert module.training and callback.viewer is None and stopped == [True]


def test_the_live_view_renders_without_gradients_and_leaves_the_module_training(tmp_path):
    """The module is not switched to eval for a frame: what a render would bake (the proposal sampler's grids) is not
    baked while it trains."""
    pytest.importorskip("viser")
    module = torch.nn.Linear(1, 1)
    module.train()
    seen = []
    viewer = _FakeViewer(lambda: seen.append((torch.is_grad_enabled(), module.training)))
    callback = _live_viewer(tmp_path, viewer)
    callback.on_train_batch_end(SimpleNamespace(callback_metrics={"train/psnr": torch.tensor(21.0)}, global_step=3), module, None, None, 0)
    assert seen == [(False, True)] and module.training and torch.is_grad_enabled()
    assert viewer.shown == "training: step 3, train PSNR 21.00 dB; 0 frames rendered"


# -- in the browser -----------------------------------------------------------------------------------------------


def _canvas(page) -> np.ndarray:
    """The page's screenshot left of the control panel and below the notifications: (H, W, 3) int."""
    import imageio.v3 as iio

    picture = iio.imread(page.screenshot(), extension=".png")[..., :3].astype(int)
    return picture[160:, :440]


def _choose(page, label: str, option: str) -> None:
    """Pick ``option`` in the page's dropdown ``label``, as a user clicks it."""
    page.get_by_label(label, exact=True).click()
    page.get_by_role("option", name=option, exact=True).click()


def viewer_as_nerf_view_builds_it(trained, tmp_path, max_resolution: int):
    """The viewer nerf-view starts for the ``trained`` checkpoint, built as it builds it, to look inside
    (test_nerf_view_serves_its_page_until_ctrl_c runs the command itself): -> (viewer, port, model, datamodule)."""
    from nerf_lightning.checkpoints import load_model, load_run_data
    from nerf_lightning.viz.viewer import FieldViewer
    from nerf_lightning.viz.viser_view import start_server

    port = free_port()
    server = start_server("127.0.0.1", port)
    model, info = load_model(trained["ckpt"], "cpu")
    datamodule = load_run_data(info["config"])
    viewer = FieldViewer(server, model, datamodule.scene.train, datamodule.render_views, tmp_path / "renders", max_resolution=max_resolution)
    return viewer, port, model, datamodule


@needs_browser
def test_nerf_view_in_the_browser(trained, browser, scene_cache, monkeypatch, tmp_path):
    """The page connects; it shows the rendered field (its colours, not a blank canvas); a drag in the page moves the
    camera and changes the picture; the depth view differs from the rgb one; a training camera looked through shows its
    image; the Render button writes the path's GIF."""
    monkeypatch.setenv("NERF_LIGHTNING_CACHE", str(scene_cache))
    viewer, port, _, _ = viewer_as_nerf_view_builds_it(trained, tmp_path, max_resolution=256)
    try:
        page, client_id = open_page(browser, viewer, port)
        viewer.page.show_cameras.value = False  # the frustums show the training images: keep them out of the picture
        viewer.page.set_cameras_visible(False)
        wait_for(lambda: viewer.scheduler.settled(client_id), what="the first view to be refined")
        frame = viewer.last_frame[client_id]
        assert frame["height"] == 256 and frame["output"] == "rgb"
        time.sleep(1.0)
        first = _canvas(page)
        page.screenshot(path=str(tmp_path / "view.png"))  # kept for a look when the test fails
        # the page shows the rendered picture: the screenshot matches the frame stretched over the canvas
        picture = torch.nn.functional.interpolate(torch.from_numpy(frame["picture"]).permute(2, 0, 1)[None].float(),
                                                  size=(600, 800), mode="bilinear")[0].permute(1, 2, 0).numpy()[160:, :440]
        assert np.abs(first - picture).mean() < 12.0, "the screenshot is not the rendered frame"
        assert first.std(axis=(0, 1)).mean() > 10.0, "the canvas is blank"
        scene = (np.abs(first - 255).max(axis=-1) > 60).sum()  # the scene's objects on the white background
        assert scene > 0.1 * first.shape[0] * first.shape[1], f"only {scene} pixels of the scene in the screenshot"

        version = viewer.scheduler.version(client_id)
        page.mouse.move(200, 400)
        page.mouse.down()
        page.mouse.move(330, 380, steps=12)
        page.mouse.up()
        wait_for(lambda: viewer.scheduler.version(client_id) > version and viewer.scheduler.settled(client_id), what="the moved camera's frame")
        time.sleep(1.0)
        moved = _canvas(page)
        assert np.abs(moved - first).mean() > 5.0, "dragging in the page did not change the picture"

        _choose(page, "Show", "depth")
        wait_for(lambda: viewer.last_frame[client_id]["output"] == "depth" and viewer.scheduler.settled(client_id), what="the depth view")
        time.sleep(1.0)
        depth = _canvas(page)
        assert np.abs(depth - moved).mean() > 10.0, "the depth view looks like the rgb one"

        # a training camera, looked through (what a click on its frustum does), shows its training image
        _choose(page, "Show", "rgb")
        viewer.page.look_through(viewer.server.get_clients()[client_id], 3)
        train = viewer.page.train_views
        wait_for(lambda: np.allclose(viewer.scheduler.camera(client_id).position, train.c2w[3, :3, 3].numpy(), atol=1e-3)
              and viewer.last_frame[client_id]["output"] == "rgb" and viewer.scheduler.settled(client_id), what="the view through camera 3")
        seen = torch.from_numpy(viewer.last_frame[client_id]["picture"]).permute(2, 0, 1)[None].float() / 255.0
        image = torch.nn.functional.interpolate(train.images[3].permute(2, 0, 1)[None].float() / 255.0, size=seen.shape[-2:], mode="area")
        crop = min(image.shape[-1], seen.shape[-1])  # the browser's aspect may be wider: compare the middle
        left_seen, left_image = (seen.shape[-1] - crop) // 2, (image.shape[-1] - crop) // 2
        mse = torch.mean((seen[..., left_seen:left_seen + crop] - image[..., left_image:left_image + crop]) ** 2)
        assert float(mse_to_psnr(mse)) > 15.0

        viewer.page.path_frames.value, viewer.page.path_scale.value = 4, 0.25
        page.get_by_role("button", name="Render to GIF").click()
        wait_for(lambda: "wrote" in viewer.page.path_status.content, seconds=120, what="the orbit GIF")
        gifs = list((tmp_path / "renders").glob("*_orbit/rgb.gif"))
        assert len(gifs) == 1 and viewer.page.path_status.content == f"wrote {gifs[0]}"
    finally:
        viewer.stop()
        viewer.server.stop()


@pytest.mark.slow  # half a minute of browser; test_nerf_view_in_the_browser drives the page in CI
@needs_browser
def test_a_path_framed_in_the_browser_is_saved_and_rendered(trained, browser, scene_cache, monkeypatch, tmp_path):
    """The page's Camera path folder: three views added as keyframes with its button, the second removed, the preview
    drawn, the path saved as camera_path.json (one second at 3 frames a second); nerf-render renders it: three frames,
    the first and the last the two keyframes' views, the middle one between them."""
    from tests.conftest import run_cli

    monkeypatch.setenv("NERF_LIGHTNING_CACHE", str(scene_cache))
    viewer, port, model, datamodule = viewer_as_nerf_view_builds_it(trained, tmp_path, max_resolution=64)
    train, panel = datamodule.scene.train, viewer.page.keyframes
    try:
        page, client_id = open_page(browser, viewer, port)
        for count, index in enumerate((3, 20, 12), start=1):
            viewer.page.look_through(viewer.server.get_clients()[client_id], index)
            wait_for(lambda: np.allclose(viewer.server.get_clients()[client_id].camera.position, train.c2w[index, :3, 3].numpy(), atol=1e-3),
                     what=f"the view through camera {index}")
            page.get_by_role("button", name="Add keyframe").click()
            wait_for(lambda: len(panel.keyframes) == count, what=f"keyframe {count}")
        assert panel.listing.content.count("\n") == 2  # three lines, one a keyframe
        panel.remove_index.value = 2
        page.get_by_role("button", name="Remove keyframe").click()
        wait_for(lambda: len(panel.keyframes) == 2, what="the second keyframe removed")
        panel.seconds.value, panel.fps.value = 1.0, 3.0
        page.get_by_label("Preview path", exact=True).click()
        wait_for(lambda: panel.preview.value, what="the preview")
        page.get_by_role("button", name="Save camera_path.json").click()
        wait_for(lambda: panel.saved is not None and "saved" in panel.status.content, what="camera_path.json")
    finally:
        viewer.stop()
        viewer.server.stop()
    saved = panel.saved
    assert saved == tmp_path / "renders" / "camera_paths" / "camera_path.json"
    meta = json.loads(saved.read_text())
    assert len(meta["keyframes"]) == 2 and len(meta["camera_path"]) == 3 and meta["fps"] == 3.0

    run_cli("render", f"ckpt_path={trained['ckpt']}", f"render.path={saved}", f"output_dir={tmp_path / 'render'}", "device=cpu", cwd=tmp_path)
    import imageio.v3 as iio

    frames = [torch.from_numpy(iio.imread(path)).float() / 255.0 for path in sorted((tmp_path / "render" / "frames").glob("rgb_*.png"))]
    assert len(frames) == 3 and frames[0].shape == (train.height, train.width, 3)
    ends = [model.render_view(train.K[index], train.c2w[index], train.height, train.width)["rgb"].clamp(0, 1) for index in (3, 12)]
    assert float(mse_to_psnr(torch.mean((frames[0] - ends[0]) ** 2))) > 35.0
    assert float(mse_to_psnr(torch.mean((frames[2] - ends[1]) ** 2))) > 35.0
    assert all(float(mse_to_psnr(torch.mean((frames[1] - end) ** 2))) < 30.0 for end in ends)


@pytest.mark.slow  # two trainings side by side (half a minute): out of CI, which the browser test above keeps the viewer in
@needs_browser
def test_training_with_a_live_view_reaches_the_same_psnr_and_outlives_the_browser(trained, browser, scene_cache, tmp_path):
    """nerf-train viewer=live with a browser that connects mid-run, then goes away: the run finishes, within 0.5 dB of
    the same run without the view, and rendered at most about 10% of the time."""
    port = free_port()
    env = dict(os.environ, NERF_LIGHTNING_CACHE=str(scene_cache), PYTHONUNBUFFERED="1")
    run_dir = tmp_path / "live"
    command = [sys.executable, "-m", "nerf_lightning.cli.train", *RUN, "viewer=live", f"callbacks.viewer.port={port}", f"paths.output_dir={run_dir}"]
    log_path = tmp_path / "train.log"
    with open(log_path, "w") as log:
        run = subprocess.Popen(command, cwd=tmp_path, env=env, stdout=log, stderr=subprocess.STDOUT)
        try:
            wait_for(lambda: "live view of the training field" in log_path.read_text() or run.poll() is not None, what="the live view")
            assert run.poll() is None, log_path.read_text()[-3000:]
            page = browser.new_page(viewport={"width": 640, "height": 480})
            page.goto(f"http://127.0.0.1:{port}/")
            def frames_shown() -> int:
                found = re.findall(r"(\d+) frames rendered", page.content())
                return int(found[-1]) if found else 0

            # the page follows training: the picture is rendered again as the field changes
            wait_for(lambda: frames_shown() >= 3 or run.poll() is not None, seconds=120, what="three frames in the page")
            assert run.poll() is None, "the run ended before the page showed three frames"
            page.close()  # the browser goes away mid-run
            assert run.wait(timeout=600) == 0, log_path.read_text()[-3000:]
        finally:
            if run.poll() is None:
                run.kill()
    text = log_path.read_text()
    match = re.search(r"live viewer: (\d+) frames, ([\d.]+) s of rendering, ([\d.]+)% of training", text)
    assert match, text[-3000:]
    frames, share = int(match.group(1)), float(match.group(3))
    assert frames >= 1 and share <= 12.0
    psnr = json.loads((run_dir / "metrics.json").read_text())["val/psnr"]
    assert abs(psnr - trained["psnr"]) < 0.5, f"with the view {psnr:.2f} dB, without {trained['psnr']:.2f} dB"
