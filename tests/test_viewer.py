"""nerf-view and nerf-train viewer=true: the pieces without a browser, then the page in headless Debian chromium
(driven by Playwright), as a user would use it."""

from __future__ import annotations

import importlib.util
import json
import math
import os
import re
import shutil
import socket
import subprocess
import sys
import threading
import time
from pathlib import Path

import kornia
import numpy as np
import pytest
import torch

from nerf_lightning.config import compose_config
from nerf_lightning.metrics import mse_to_psnr
from nerf_lightning.rendering.views import render_view
from nerf_lightning.viz.viewer import browser_camera, occupied_cells, progressive_heights, scene_box
from nerf_lightning.viz.viser_view import check_port

CHROMIUM = shutil.which("chromium")
needs_browser = pytest.mark.skipif(CHROMIUM is None, reason="Debian's chromium is not installed (.ci/run installs it)")

# a short run of the fast preset: 150 steps, a 32^3 occupancy grid
RUN = ["experiment=fast", "trainer.max_steps=150", "model.sampler.grid.resolution=32", "data.val_every=150",
       "trainer.enable_progress_bar=false", "trainer.enable_model_summary=false"]


def _free_port() -> int:
    with socket.socket() as probe:
        probe.bind(("127.0.0.1", 0))
        return probe.getsockname()[1]


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
    frame = render_view(model, train.K[3], train.c2w[3], train.height, train.width, chunk_size=4096)
    target = train.images[3].float() / 255.0
    assert float(mse_to_psnr(torch.mean((frame["rgb"] - target) ** 2))) > 15.0
    assert render_view(model, train.K[3], train.c2w[3], train.height, train.width, chunk_size=64, abort=lambda: True) is None


def test_scene_box_and_occupied_cells_in_the_world(trained):
    model = trained["model"]
    edges = scene_box(model)
    assert edges.shape == (12, 2, 3) and np.allclose(np.abs(edges), 1.3)  # the fast preset's field box
    points, size = occupied_cells(model)
    assert 0 < len(points) < 32**3 and size == pytest.approx(2.6 / 32)
    assert (np.abs(points) <= 1.3).all()


def test_a_taken_port_is_named(tmp_path, procedural_scene):
    with socket.socket() as holder:
        holder.bind(("127.0.0.1", 0))
        holder.listen()
        port = holder.getsockname()[1]
        with pytest.raises(ValueError, match=f"port {port} on 127.0.0.1 is taken.*viewer_port=<port>"):
            check_port("127.0.0.1", port, "viewer_port")
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
    for module, args in (("view", ["ckpt_path=any.ckpt"]), ("train", ["experiment=fast", "viewer=true", f"paths.output_dir={tmp_path / 'run'}"])):
        result = subprocess.run([sys.executable, "-m", f"nerf_lightning.cli.{module}", *args], cwd=tmp_path, env=env,
                                capture_output=True, text=True, timeout=120)
        assert result.returncode == 2, result.stderr
        assert 'needs viser, an optional extra: pip install -e ".[viz]"' in result.stderr.strip().splitlines()[-1]


def test_viewer_true_refuses_an_image_field(tmp_path):
    pytest.importorskip("viser")
    from nerf_lightning.training import train

    with pytest.raises(ValueError, match="viewer=true shows a radiance field"):
        train(compose_config(["viewer=true", f"paths.output_dir={tmp_path}"]))


def test_an_error_in_the_live_view_is_reported_once_and_training_goes_on(caplog, tmp_path):
    pytest.importorskip("viser")
    from types import SimpleNamespace

    from nerf_lightning.viz.viewer import LiveViewer

    class Broken:
        frames_rendered, path_requested = 0, False
        show_cells = SimpleNamespace(value=False)
        training = SimpleNamespace(content="")

        def render_next(self):
            raise RuntimeError("the socket went away")

    stopped = []
    callback = LiveViewer(port=_free_port(), output_dir=tmp_path)
    callback.viewer = Broken()
    callback.server = SimpleNamespace(get_clients=lambda: {1: object()}, stop=lambda: stopped.append(True))
    callback._started = time.perf_counter() - 100.0
    module, trainer = torch.nn.Linear(1, 1), SimpleNamespace(callback_metrics={}, global_step=7)
    module.train()
    with caplog.at_level("WARNING"):
        for _ in range(3):  # the step after the error and those after it: no exception, one warning
            callback.on_train_batch_end(trainer, module, None, None, 0)
    warnings = [r for r in caplog.records if "live viewer stopped" in r.getMessage()]
    assert len(warnings) == 1 and "RuntimeError: the socket went away" in warnings[0].getMessage()
    assert module.training and callback.viewer is None and stopped == [True]


def test_the_live_view_runs_the_proposal_networks_unbaked_and_leaves_the_setting_as_it_was(tmp_path):
    pytest.importorskip("viser")
    from types import SimpleNamespace

    from nerf_lightning.viz.viewer import LiveViewer

    module = torch.nn.Module()
    module.sampler = SimpleNamespace(bake_resolution=128)
    seen = []

    class Recorder:
        frames_rendered, path_requested = 0, False
        show_cells = SimpleNamespace(value=False)
        training = SimpleNamespace(content="")

        def render_next(self):  # the weights change at every step: baking them for one frame would cost more than it saves
            seen.append((module.sampler.bake_resolution, module.training))

    callback = LiveViewer(port=_free_port(), output_dir=tmp_path)
    callback.viewer = Recorder()
    callback.server = SimpleNamespace(get_clients=lambda: {1: object()}, stop=lambda: None)
    callback._started = time.perf_counter() - 100.0
    callback.on_train_batch_end(SimpleNamespace(callback_metrics={}, global_step=3), module, None, None, 0)
    assert seen == [(None, False)]
    assert module.sampler.bake_resolution == 128 and module.training


# -- in the browser -----------------------------------------------------------------------------------------------


@pytest.fixture
def browser():
    pytest.importorskip("viser")
    playwright = pytest.importorskip("playwright.sync_api")
    if CHROMIUM is None:
        pytest.skip("Debian's chromium is not installed (.ci/run installs it)")
    with playwright.sync_playwright() as driver:
        chromium = driver.chromium.launch(executable_path=CHROMIUM, args=["--no-sandbox", "--disable-gpu"])
        yield chromium
        chromium.close()


def _wait(condition, seconds: float = 60.0, what: str = "") -> None:
    deadline = time.monotonic() + seconds
    while time.monotonic() < deadline:
        if condition():
            return
        time.sleep(0.1)
    pytest.fail(f"waited {seconds:.0f} s for {what}")


def _canvas(page) -> np.ndarray:
    """The page's screenshot left of the control panel and below the notifications: (H, W, 3) int."""
    import imageio.v3 as iio

    picture = iio.imread(page.screenshot(), extension=".png")[..., :3].astype(int)
    return picture[160:, :440]


def _choose(page, label: str, option: str) -> None:
    """Pick ``option`` in the page's dropdown ``label``, as a user clicks it."""
    page.get_by_label(label, exact=True).click()
    page.get_by_role("option", name=option, exact=True).click()


def _settled(viewer, client_id) -> bool:
    """The browser's camera has been rendered to the last progressive step."""
    with viewer._lock:
        state = viewer._clients.get(client_id)
        return state is not None and state.camera is not None and state.rendered_version == state.version \
            and state.rendered_height >= viewer._heights(state)[-1]


@needs_browser
def test_nerf_view_in_the_browser(trained, browser, scene_cache, monkeypatch, tmp_path):
    """The page connects; it shows the rendered field (its colours, not a blank canvas); a drag in the page moves the
    camera and changes the picture; the depth view differs from the rgb one; a training camera looked through shows its
    image; the Render button writes the path's GIF."""
    from nerf_lightning.cli.view import view

    monkeypatch.setenv("NERF_LIGHTNING_CACHE", str(scene_cache))
    port = _free_port()
    cfg = compose_config([f"ckpt_path={trained['ckpt']}", f"port={port}", "device=cpu", f"output_dir={tmp_path / 'renders'}",
                          "view.max_resolution=256"], config_name="view")
    viewer = view(cfg)
    loop = threading.Thread(target=viewer.serve_forever, daemon=True)
    loop.start()
    try:
        page = browser.new_page(viewport={"width": 800, "height": 600})
        page.goto(f"http://127.0.0.1:{port}/")
        _wait(lambda: len(viewer.server.get_clients()) == 1, what="the page to connect")
        client_id = next(iter(viewer.server.get_clients()))
        viewer.show_cameras.value = False  # the frustums show the training images: keep them out of the picture
        viewer._set_cameras_visible(False)
        _wait(lambda: _settled(viewer, client_id), what="the first view to be refined")
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

        version = viewer._clients[client_id].version
        page.mouse.move(200, 400)
        page.mouse.down()
        page.mouse.move(330, 380, steps=12)
        page.mouse.up()
        _wait(lambda: viewer._clients[client_id].version > version and _settled(viewer, client_id), what="the moved camera's frame")
        time.sleep(1.0)
        moved = _canvas(page)
        assert np.abs(moved - first).mean() > 5.0, "dragging in the page did not change the picture"

        _choose(page, "Show", "depth")
        _wait(lambda: viewer.last_frame[client_id]["output"] == "depth" and _settled(viewer, client_id), what="the depth view")
        time.sleep(1.0)
        depth = _canvas(page)
        assert np.abs(depth - moved).mean() > 10.0, "the depth view looks like the rgb one"

        # a training camera, looked through (what a click on its frustum does), shows its training image
        _choose(page, "Show", "rgb")
        viewer.look_through(viewer.server.get_clients()[client_id], 3)
        train = viewer.train_views
        _wait(lambda: np.allclose(viewer._clients[client_id].camera[1], train.c2w[3, :3, 3].numpy(), atol=1e-3)
              and viewer.last_frame[client_id]["output"] == "rgb" and _settled(viewer, client_id), what="the view through camera 3")
        seen = torch.from_numpy(viewer.last_frame[client_id]["picture"]).permute(2, 0, 1)[None].float() / 255.0
        image = torch.nn.functional.interpolate(train.images[3].permute(2, 0, 1)[None].float() / 255.0, size=seen.shape[-2:], mode="area")
        crop = min(image.shape[-1], seen.shape[-1])  # the browser's aspect may be wider: compare the middle
        left_seen, left_image = (seen.shape[-1] - crop) // 2, (image.shape[-1] - crop) // 2
        mse = torch.mean((seen[..., left_seen:left_seen + crop] - image[..., left_image:left_image + crop]) ** 2)
        assert float(mse_to_psnr(mse)) > 15.0

        viewer.path_frames.value, viewer.path_scale.value = 4, 0.25
        page.get_by_role("button", name="Render to GIF").click()
        _wait(lambda: "wrote" in viewer.path_status.content, seconds=120, what="the orbit GIF")
        gifs = list((tmp_path / "renders").glob("*_orbit/rgb.gif"))
        assert len(gifs) == 1 and viewer.path_status.content == f"wrote {gifs[0]}"
    finally:
        viewer.stop()
        viewer.server.stop()


@needs_browser
def test_training_with_a_live_view_reaches_the_same_psnr_and_outlives_the_browser(trained, browser, scene_cache, tmp_path):
    """nerf-train viewer=true with a browser that connects mid-run, then goes away: the run finishes, within 0.5 dB of
    the same run without the view, and rendered at most about 10% of the time."""
    port = _free_port()
    env = dict(os.environ, NERF_LIGHTNING_CACHE=str(scene_cache), PYTHONUNBUFFERED="1")
    run_dir = tmp_path / "live"
    command = [sys.executable, "-m", "nerf_lightning.cli.train", *RUN, "viewer=true", f"viewer_port={port}", f"paths.output_dir={run_dir}"]
    log_path = tmp_path / "train.log"
    with open(log_path, "w") as log:
        run = subprocess.Popen(command, cwd=tmp_path, env=env, stdout=log, stderr=subprocess.STDOUT)
        try:
            _wait(lambda: "live view of the training field" in log_path.read_text() or run.poll() is not None, what="the live view")
            assert run.poll() is None, log_path.read_text()[-3000:]
            page = browser.new_page(viewport={"width": 640, "height": 480})
            page.goto(f"http://127.0.0.1:{port}/")
            def frames_shown() -> int:
                found = re.findall(r"(\d+) frames rendered", page.content())
                return int(found[-1]) if found else 0

            # the page follows training: the picture is rendered again as the field changes
            _wait(lambda: frames_shown() >= 3 or run.poll() is not None, seconds=120, what="three frames in the page")
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
