"""nerf-view and the live view of a Gaussian-splat model: its Gaussians drawn by the browser (viser's splats) in the
world where the viewer puts the training cameras, at most the most opaque ones, sent again as the model trains, and
the page in headless Debian chromium (Playwright)."""

from __future__ import annotations

import math
import time
from types import SimpleNamespace

import numpy as np
import pytest
import torch

from nerf_lightning.geometry.space import SceneSpace
from tests.viz.conftest import free_port, needs_browser, open_page, wait_for

QUICK = ["experiment=splat_procedural", "data.scene.size=32", "model.start.random.count=3000"]
VIEW = 3  # the training camera the Gaussians are placed in front of


def splat_model(make_config, means: torch.Tensor, colours: torch.Tensor, log_scales: torch.Tensor | float,
                opacity_logits: torch.Tensor | float):
    """A SplatModule of the splat preset (as tests/models/test_splat.py builds one) holding exactly these Gaussians
    (random rotations, degree-0 colours ``colours``), in eval mode."""
    from hydra.utils import instantiate

    model = instantiate(make_config(*QUICK).model)
    model.gaussians.initialise(means, colours, torch.Generator().manual_seed(0))
    with torch.no_grad():
        model.gaussians.log_scales.copy_(torch.as_tensor(log_scales, dtype=torch.float32).expand_as(model.gaussians.log_scales))
        model.gaussians.opacity_logits.copy_(torch.as_tensor(opacity_logits, dtype=torch.float32).expand_as(model.gaussians.opacity_logits))
    return model.eval()


class FrameModel:
    """A model that renders a grey picture and has no Gaussians (a NeRF, to the viewer)."""

    device = torch.device("cpu")
    space = SceneSpace(2.0, 6.0, (1.0, 1.0, 1.0))  # the contract's: the page writes camera paths through its world_from_capture

    def render_view(self, K, c2w, height, width, abort=None):
        return {"rgb": torch.full((height, width, 3), 0.5), "depth": torch.ones(height, width), "accumulation": torch.ones(height, width)}


@pytest.fixture
def server(monkeypatch):
    """A viser server whose ``add_gaussian_splats`` calls are recorded in ``server.sent`` (name, arrays)."""
    viser = pytest.importorskip("viser")
    server = viser.ViserServer(host="127.0.0.1", port=free_port(), verbose=False)
    server.sent = []
    original = server.scene.add_gaussian_splats

    def recording(name, **arrays):
        server.sent.append((name, {key: np.array(value) for key, value in arrays.items() if isinstance(value, np.ndarray)}))
        return original(name, **arrays)

    monkeypatch.setattr(server.scene, "add_gaussian_splats", recording)
    yield server
    server.stop()


def _quaternion_matrix(q: np.ndarray) -> np.ndarray:
    """(N, 4) w x y z -> (N, 3, 3), written out (not the project's code)."""
    w, x, y, z = (q / np.linalg.norm(q, axis=-1, keepdims=True)).T
    return np.stack([
        np.stack([1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)], -1),
        np.stack([2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)], -1),
        np.stack([2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)], -1),
    ], -2)


def _in_front_of(train, pixels: list[tuple[float, float]], depth: float) -> torch.Tensor:
    """World points ``depth`` along training camera VIEW's axis (its z) seen at ``pixels`` (u right, v down)."""
    K, c2w = train.K[VIEW].double(), train.c2w[VIEW].double()
    uv1 = torch.tensor([[u, v, 1.0] for u, v in pixels], dtype=torch.float64)
    camera = (torch.linalg.inv(K) @ uv1.T).T * depth
    return (camera @ c2w[:3, :3].T + c2w[:3, 3]).float()


# -- without a browser --------------------------------------------------------------------------------------------


def test_the_splats_sent_are_the_models_gaussians_where_the_viewer_puts_its_cameras(server, procedural_scene, make_config, tmp_path):
    """The browser is sent the Gaussians as they are (centres, R S S^T R^T, degree-0 colours, opacities), with no
    frame rendered; projected through training camera VIEW's frustum as the page places it, each centre lands on the
    pixel where the model's own render of that camera shows its colour."""
    import viser.transforms

    from nerf_lightning.viz.viewer import FieldViewer

    train = procedural_scene.train
    pixels = [(20.5, 20.5), (75.5, 25.5), (30.5, 70.5), (70.5, 75.5)]
    depth = 3.5
    colours = torch.tensor([[0.9, 0.1, 0.1], [0.1, 0.8, 0.2], [0.15, 0.2, 0.9], [0.85, 0.75, 0.1]])
    # about two pixels across, a little longer one way than the others
    log_scales = math.log(2.0 * depth / float(train.K[VIEW, 0, 0])) + torch.tensor([0.0, -0.3, 0.2])
    model = splat_model(make_config, _in_front_of(train, pixels, depth), colours, log_scales, 8.0)
    g = model.gaussians

    viewer = FieldViewer(server, model, train, lambda path, frames: train.subset([0, 1]), tmp_path)
    assert viewer.page.splats_drawn and viewer.page.output.disabled  # the browser draws them: no frame to choose
    viewer.scheduler.connect(7)  # a browser, as the page reports it, with its camera
    viewer.scheduler.camera_moved(7, _browser_camera(train))
    assert viewer.render_next() is not None and viewer.render_next() is None  # the splats, once; then nothing is due
    assert viewer.frames_rendered == 0 and len(server.sent) == 1

    name, sent = server.sent[0]
    assert name == "/splats" and sent["centers"].shape == (4, 3) and sent["opacities"].shape == (4, 1)
    np.testing.assert_allclose(sent["centers"], g.means.detach().numpy(), atol=1e-6)
    rotations = _quaternion_matrix(g.quats.detach().double().numpy())
    expected = rotations @ (np.exp(2.0 * g.log_scales.detach().double().numpy())[:, :, None] * rotations.transpose(0, 2, 1))
    np.testing.assert_allclose(sent["covariances"], expected, rtol=1e-4, atol=1e-9)
    np.testing.assert_allclose(sent["rgbs"], colours.numpy(), atol=1e-5)  # sh0 back to the colours it was made from
    np.testing.assert_allclose(sent["opacities"], 1.0 / (1.0 + math.exp(-8.0)), rtol=1e-6)
    buffer = viewer.page.splat_handle.buffer  # what viser holds for the browsers: float32 centres first
    np.testing.assert_array_equal(np.ascontiguousarray(buffer[:, :3]).view(np.float32), sent["centers"])
    assert "all 4 Gaussians" in viewer.page.stats.content and "degree-0" in viewer.page.stats.content

    # training camera VIEW, as the page draws its frustum (viser's wxyz, position and vertical fov of an OpenCV camera)
    frustum = viewer.page.frustums[VIEW]
    rotation, position = viser.transforms.SO3(np.asarray(frustum.wxyz)).as_matrix(), np.asarray(frustum.position)
    focal = 0.5 * train.height / math.tan(0.5 * frustum.fov)
    seen = (sent["centers"] - position) @ rotation  # world -> that camera
    assert (seen[:, 2] > 0).all()
    uv = focal * seen[:, :2] / seen[:, 2:] + np.array([float(train.K[VIEW, 0, 2]), float(train.K[VIEW, 1, 2])])
    np.testing.assert_allclose(uv, np.array(pixels), atol=0.05)
    frame = model.render_view(train.K[VIEW], train.c2w[VIEW], train.height, train.width)["rgb"]
    for (u, v), rgb in zip(pixels, sent["rgbs"]):
        np.testing.assert_allclose(frame[int(v), int(u)].numpy(), rgb, atol=0.03)

    # the higher bands colour rendered frames only: the browser's colours are the same from everywhere
    with torch.no_grad():
        g.shN.normal_(0.0, 0.5, generator=torch.Generator().manual_seed(1))
    viewer.refresh_splats("higher bands")
    viewer.render_next()
    np.testing.assert_allclose(server.sent[-1][1]["rgbs"], colours.numpy(), atol=1e-5)


def _browser_camera(train):
    """A browser's camera where training camera VIEW is (as the page reports it to the scheduler)."""
    import kornia

    from nerf_lightning.viz.scheduler import BrowserCamera

    c2w = train.c2w[VIEW]
    wxyz = kornia.geometry.conversions.rotation_matrix_to_quaternion(c2w[:3, :3].contiguous()).numpy()
    fov_y = 2.0 * math.atan(0.5 * train.height / float(train.K[VIEW, 1, 1]))
    return BrowserCamera(wxyz, c2w[:3, 3].numpy(), fov_y, train.width / train.height, train.height)


def test_rendered_frames_are_a_choice_in_the_page_and_a_model_without_gaussians_has_none(server, procedural_scene, make_config, tmp_path):
    from nerf_lightning.viz.page import FRAMES, SPLATS
    from nerf_lightning.viz.viewer import FieldViewer

    train = procedural_scene.train
    model = splat_model(make_config, _in_front_of(train, [(50.5, 50.5)], 3.5), torch.tensor([[0.9, 0.1, 0.1]]), math.log(0.05), 4.0)
    viewer = FieldViewer(server, model, train, lambda path, frames: train.subset([0, 1]), tmp_path, max_resolution=32)
    viewer.scheduler.connect(7)
    viewer.scheduler.camera_moved(7, _browser_camera(train))
    viewer.render_next()
    assert viewer.splats_sent == 1 and viewer.page.splat_handle.visible

    viewer.page.drawn_by.value = FRAMES  # as the page's dropdown sets it
    assert not viewer.page.splat_handle.visible and not viewer.page.output.disabled
    assert viewer.render_next() is not None and viewer.frames_rendered == 1  # through render_view, as a NeRF's
    viewer.page.drawn_by.value = SPLATS
    assert viewer.page.splat_handle.visible and viewer.page.output.disabled and "all 1 Gaussians" in viewer.page.stats.content
    assert viewer.render_next() is None and viewer.splats_sent == 1  # the model did not change: nothing is sent again

    nerf = FieldViewer(server, FrameModel(), train, lambda path, frames: train.subset([0, 1]), tmp_path, max_resolution=32)
    assert nerf.page.drawn_by is None and not nerf.has_gaussians and not nerf.page.splats_drawn
    nerf.scheduler.connect(8)
    nerf.scheduler.camera_moved(8, _browser_camera(train))
    assert nerf.render_next() is not None and nerf.frames_rendered == 1 and nerf.splats_sent == 0


def test_a_large_model_sends_its_most_opaque_gaussians_and_says_how_many(server, procedural_scene, make_config, tmp_path):
    from nerf_lightning.viz.splats import MAX_SPLATS, splat_arrays
    from nerf_lightning.viz.viewer import FieldViewer

    generator = torch.Generator().manual_seed(0)
    logits = torch.linspace(-4.0, 4.0, 60)[torch.randperm(60, generator=generator)]
    model = splat_model(make_config, torch.randn(60, 3, generator=generator), torch.rand(60, 3, generator=generator), math.log(0.05), logits)
    with torch.no_grad():
        model.gaussians.means[int(logits.argmax())] = float("nan")  # a diverged one is left out, however opaque
    train = procedural_scene.train
    viewer = FieldViewer(server, model, train, lambda path, frames: train.subset([0, 1]), tmp_path, max_splats=10)
    viewer.render_next()
    sent = server.sent[-1][1]
    finite = torch.isfinite(model.gaussians.means).all(-1)
    kept = torch.nonzero(finite).squeeze(-1)
    kept = kept[logits[kept].argsort(descending=True)[:10]].sort().values  # the 10 most opaque finite ones, in order
    np.testing.assert_allclose(sent["opacities"][:, 0], torch.sigmoid(logits[kept]).numpy(), rtol=1e-6)
    np.testing.assert_allclose(sent["centers"], model.gaussians.means.detach()[kept].numpy())
    assert viewer.splats_shown == 10
    assert "the 10 most opaque of 60 Gaussians" in viewer.page.stats.content
    assert MAX_SPLATS == 1_000_000 and len(splat_arrays(model).centers) == 59
    assert FieldViewer.__init__.__defaults__[-1] == MAX_SPLATS


def test_the_live_view_sends_the_splats_again_as_they_train(server, procedural_scene, make_config, tmp_path):
    """Every ``splats_every_s`` of wall time while a browser watches: new splats after the model changed (here its
    count), nothing when no step was taken, nothing before the time is up."""
    from nerf_lightning.viz.live import LiveViewer
    from nerf_lightning.viz.viewer import FieldViewer

    train = procedural_scene.train
    generator = torch.Generator().manual_seed(0)
    model = splat_model(make_config, torch.randn(20, 3, generator=generator), torch.rand(20, 3, generator=generator), math.log(0.05), 2.0)
    model.train()
    viewer = FieldViewer(server, model, train, lambda path, frames: train.subset([0, 1]), tmp_path)
    callback = LiveViewer(port=free_port(), output_dir=tmp_path)
    assert callback.splats_every_s == 3.0
    callback.viewer = viewer
    callback.server = SimpleNamespace(get_clients=lambda: {1: object()}, stop=lambda: None)  # a browser watches
    callback._started = time.perf_counter() - 100.0
    trainer = SimpleNamespace(callback_metrics={}, global_step=1)

    def step(number: int, seconds_later: float = 0.0) -> None:
        trainer.global_step = number
        callback._splats_refreshed_at -= seconds_later  # as if that much wall time had passed
        callback.on_train_batch_end(trainer, model, None, None, 0)

    step(1)
    assert viewer.splats_sent == 1 and server.sent[-1][1]["centers"].shape == (20, 3)
    assert "20 Gaussians drawn by the browser" in viewer.page.training.content
    step(1, seconds_later=10.0)  # no step taken since: nothing read, nothing sent
    assert viewer.splats_sent == 1

    with torch.no_grad():  # densification: the count changes
        model.gaussians.initialise(torch.randn(35, 3, generator=generator), torch.rand(35, 3, generator=generator), generator)
    step(2)  # a second later: not yet
    assert viewer.splats_sent == 1
    step(3, seconds_later=3.5)
    assert viewer.splats_sent == 2 and len(server.sent) == 2
    assert server.sent[-1][1]["centers"].shape == (35, 3) and viewer.page.splat_handle.buffer.shape == (35, 8)
    np.testing.assert_allclose(server.sent[-1][1]["centers"], model.gaussians.means.detach().numpy())
    assert "35 Gaussians drawn by the browser" in viewer.page.training.content
    assert "all 35 Gaussians" in viewer.page.stats.content


# -- in the browser -----------------------------------------------------------------------------------------------


def _colour_centre(picture: np.ndarray, channel: int) -> tuple[np.ndarray, int]:
    """The mean (x, y) of the pixels of ``picture`` (H, W, 3) strongly of one primary ``channel``, and how many."""
    others = [c for c in range(3) if c != channel]
    mask = (picture[..., channel] > 150) & (picture[..., others].max(axis=-1) < 90)
    ys, xs = np.nonzero(mask)
    return (np.array([xs.mean(), ys.mean()]) if len(xs) else np.full(2, np.nan)), int(mask.sum())


def _canvas(page) -> np.ndarray:
    """The page's screenshot left of the control panel and below the notifications: (H, W, 3) int."""
    import imageio.v3 as iio

    picture = iio.imread(page.screenshot(), extension=".png")[..., :3].astype(int)
    return picture[160:, :440]


@needs_browser
def test_the_browser_draws_the_splats_where_the_rendered_frames_show_them(browser, procedural_scene, make_config, tmp_path):
    """The page connects and shows the Gaussians (their colours on the canvas) with no frame rendered; "rendered
    frames" (chosen as a user does) shows the model's render, with each colour where the browser drew it; back on
    the splats, a drag moves them with no frame rendered and nothing sent again."""
    from nerf_lightning.viz.viewer import FieldViewer
    from nerf_lightning.viz.viser_view import start_server

    train = procedural_scene.train
    c2w = train.c2w[0]  # where the page's camera starts, looking at where the cameras look (the origin here)
    right, down = c2w[:3, 0], c2w[:3, 1]
    # apart, left of the control panel and below the notifications: red, green left of it, blue below between them
    means = torch.stack([-0.4 * right, -1.2 * right, -0.8 * right + 0.7 * down])
    model = splat_model(make_config, means, torch.tensor([[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]]), math.log(0.12), 6.0)
    port = free_port()
    server = start_server("127.0.0.1", port)
    viewer = FieldViewer(server, model, train, lambda path, frames: train.subset([0, 1]), tmp_path / "renders", max_resolution=256)
    viewer.page.show_cameras.value = False  # the frustums show the training images: keep them out of the picture
    try:
        page, client_id = open_page(browser, viewer, port)
        shots = {}

        def shows(name: str) -> bool:
            """The canvas shows the three colours, where the previous screenshot showed them (the picture settled)."""
            previous, shots[name] = shots.get(name), _canvas(page)
            found = [_colour_centre(shots[name], channel) for channel in range(3)]
            if previous is None or min(count for _, count in found) < 300:
                return False
            return all(np.abs(centre - _colour_centre(previous, channel)[0]).max() < 0.5 for channel, (centre, _) in enumerate(found))

        wait_for(lambda: shows("splats"), what="the three splats on the canvas")
        page.screenshot(path=str(tmp_path / "splats.png"))  # kept for a look when the test fails
        assert viewer.splats_sent == 1 and viewer.frames_rendered == 0  # drawn by the browser: no frame rendered
        assert "all 3 Gaussians" in page.content()
        splats = shots["splats"]
        centres = {channel: _colour_centre(splats, channel)[0] for channel in range(3)}
        assert centres[1][0] < centres[0][0] - 50  # green left of red, blue below it, as placed
        assert centres[2][1] > centres[0][1] + 50 and centres[1][0] < centres[2][0] < centres[0][0]

        page.get_by_label("Drawn by", exact=True).click()
        page.get_by_role("option", name="rendered frames", exact=True).click()
        # the frames come coarse first, then at full height: wait for the last (the scheduler can read settled from
        # before the switch while the first, coarse frame is already counted)
        wait_for(lambda: viewer.scheduler.settled(client_id) and viewer.last_frame.get(client_id, {}).get("height") == 256,
                 what="the rendered frame at full height")
        assert viewer.frames_rendered > 0 and not viewer.page.splat_handle.visible
        wait_for(lambda: shows("frames"), what="the frame on the canvas")
        page.screenshot(path=str(tmp_path / "frames.png"))
        for channel in range(3):  # each colour where the browser drew it, within a few pixels
            drawn, rendered = _colour_centre(splats, channel)[0], _colour_centre(shots["frames"], channel)[0]
            assert np.abs(drawn - rendered).max() < 6.0, (channel, drawn, rendered)

        page.get_by_label("Drawn by", exact=True).click()
        page.get_by_role("option", name="browser splats", exact=True).click()
        wait_for(lambda: "all 3 Gaussians" in page.content() and shows("splats again"), what="the splats again")
        frames, version = viewer.frames_rendered, viewer.scheduler.version(client_id)
        before = _canvas(page)
        page.mouse.move(200, 400)
        page.mouse.down()
        page.mouse.move(330, 380, steps=12)
        page.mouse.up()
        wait_for(lambda: viewer.scheduler.version(client_id) > version, what="the camera to move")
        wait_for(lambda: np.abs(_canvas(page) - before).mean() > 3.0, what="the splats to move with the camera")
        page.screenshot(path=str(tmp_path / "moved.png"))
        assert viewer.frames_rendered == frames and viewer.splats_sent == 1  # the browser alone redrew them
    finally:
        viewer.stop()
        viewer.server.stop()
