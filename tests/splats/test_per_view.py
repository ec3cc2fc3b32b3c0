"""What splats learn a training view: the affine colour transform (model/appearance=affine) and the camera refinement
(model/camera_refinement=so3xr3). The transform starts as the identity, leaves the background as it is and lets a
view of another exposure be fitted without dragging the Gaussians' colours; a perturbed training pose is corrected;
held-out views use neither; both train in their own optimiser groups, log their penalties and load from checkpoints
(and a splat checkpoint from before them loads into a model that has them)."""

from __future__ import annotations

import math
from functools import partial

import pytest
import torch
from hydra.utils import instantiate
from kornia.geometry.conversions import axis_angle_to_rotation_matrix

from nerf_lightning.geometry.cameras import look_at
from nerf_lightning.geometry.refinement import CameraRefinement
from nerf_lightning.geometry.space import SceneSpace
from nerf_lightning.models.splat import SplatModule
from nerf_lightning.parameters.exposure import ViewExposure
from nerf_lightning.splats.appearance import ViewColourAffine
from nerf_lightning.splats.draw import PairsRasterizer
from nerf_lightning.splats.gaussians import Gaussians
from nerf_lightning.splats.projection import project
from nerf_lightning.splats.rasterize_reference import rasterize_reference
from nerf_lightning.splats.sh import rgb_to_sh
from nerf_lightning.training import train

QUICK = ["experiment=splat_procedural", "data.scene.size=32", "trainer.enable_progress_bar=false",
         "model.start.random.count=3000", "data.val_views=2"]
# gsplat's rates, the colours' ten times faster: the tiny scene below learns its colours in a few hundred steps
RATES = dict(means=1.6e-4, log_scales=5e-3, quats=1e-3, opacity_logits=5e-2, sh0=2.5e-2, shN=1.25e-4)
SIZE = 32
K = torch.tensor([[80.0, 0.0, SIZE / 2], [0.0, 80.0, SIZE / 2], [0.0, 0.0, 1.0]])


def arc_cameras(n: int, shift: float = 0.0) -> torch.Tensor:
    """(n, 4, 4) cameras 3 from the origin on a 0.6 rad arc, looking at it: every view sees the same side of the ball."""
    angles = torch.linspace(-0.3, 0.3, n) + shift
    return look_at(torch.stack([3 * angles.cos(), 3 * angles.sin(), torch.ones(n)], dim=-1))


def tiny_model(appearance: ViewColourAffine | ViewExposure | None = None, refinement: CameraRefinement | None = None) -> SplatModule:
    """400 nearly opaque Gaussians of random colours on the unit sphere (they cover every pixel of the arc's views,
    as a real capture's scene does), drawn by the pairs rasteriser; the log a no-op (no trainer)."""
    model = SplatModule(Gaussians(sh_degree=0, initial_opacity=0.9), partial(torch.optim.Adam, eps=1e-15), RATES,
                        rasterizer=PairsRasterizer(), appearance=appearance, camera_refinement=refinement)
    model.log = lambda *args, **kwargs: None
    model.use_space(SceneSpace())
    generator = torch.Generator().manual_seed(0)
    points = torch.nn.functional.normalize(torch.randn(400, 3, generator=generator), dim=-1)
    model.gaussians.initialise(points, torch.rand(400, 3, generator=generator), generator)
    return model


def fit(model: SplatModule, photos: torch.Tensor, c2w: torch.Tensor, steps: int) -> None:
    """``steps`` training steps through the module's own step and optimiser groups, the views in turn."""
    for table in model.per_view_tables().values():
        table.resize(len(photos))
    optimizer = model.configure_optimizers()
    optimizer = optimizer["optimizer"] if isinstance(optimizer, dict) else optimizer
    for step in range(steps):
        view = step % len(photos)
        loss = model.training_step({"image": photos[view], "K": K, "c2w": c2w[view], "camera_index": torch.tensor(view)}, step)
        optimizer.zero_grad()
        loss.backward()
        optimizer.step()


@pytest.fixture
def one_thread():
    """The tiny scene's steps are many small tensor operations: on one thread they take a tenth of the time they
    take on two when the machine is busy (and no more when it is not)."""
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(threads)


def psnr(a: torch.Tensor, b: torch.Tensor) -> float:
    return float(-10.0 * torch.log10((a - b).square().mean()))


@torch.no_grad()
def photos_of(model: SplatModule, c2w: torch.Tensor) -> torch.Tensor:
    return torch.stack([model.render_view(K, pose, SIZE, SIZE)["rgb"] for pose in c2w])


# -- the affine colour transform ------------------------------------------------------------------------------------


def test_zero_rows_are_the_identity_and_gradients_reach_the_drawn_views_row():
    affine = ViewColourAffine()
    affine.resize(4)
    rgb, accumulation = torch.rand(5, 6, 3), torch.rand(5, 6)
    background = torch.tensor([0.2, 0.5, 0.9])
    torch.testing.assert_close(affine(rgb, torch.tensor(2)), rgb)
    torch.testing.assert_close(affine(rgb, torch.tensor(2), accumulation, background), rgb)
    assert affine(rgb, None) is rgb  # a held-out view: no transform
    affine(rgb, torch.tensor(2), accumulation, background).square().sum().backward()
    assert affine.rows.grad[2].abs().min() > 0
    with pytest.raises(ValueError, match="camera_index must be 0-d"):
        affine(rgb, torch.tensor([1, 2]))


def test_a_row_is_an_affine_map_of_the_gaussians_colours_and_leaves_the_background():
    """Transforming the render's Gaussian part equals drawing each Gaussian with its colour transformed: the
    background, where the view is not opaque, stays the background."""
    affine = ViewColourAffine()
    affine.resize(3)
    generator = torch.Generator().manual_seed(1)
    with torch.no_grad():
        affine.rows.copy_(0.2 * torch.randn(3, 12, generator=generator))
    offset, bias = affine.offset_and_bias(torch.tensor(1))
    matrix = torch.eye(3) + offset
    # the rows are centred: their mean transform is the identity, which held-out views are drawn with
    torch.testing.assert_close(affine.centred().mean(dim=0), torch.zeros(12), atol=1e-6, rtol=0)
    rgb = torch.rand(4, 3, generator=generator)
    torch.testing.assert_close(affine(rgb, torch.tensor(1)), rgb @ matrix.T + bias)

    means = torch.randn(30, 3, generator=generator) * 0.5
    quats = torch.nn.functional.normalize(torch.randn(30, 4, generator=generator), dim=-1)
    log_scales = torch.full((30, 3), math.log(0.15))
    opacities = torch.rand(30, generator=generator) * 0.8
    colours = torch.rand(30, 3, generator=generator)
    c2w = arc_cameras(1)[0]
    background = torch.tensor([0.9, 0.1, 0.4])
    projection = project(means, quats, log_scales, opacities, K, c2w, SIZE, SIZE)
    drawn = rasterize_reference(projection, colours[projection.ids], SIZE, SIZE, background)
    assert drawn["accumulation"].min() < 0.05 and drawn["accumulation"].max() > 0.5  # background and Gaussians both seen
    transformed = rasterize_reference(projection, (colours @ matrix.T + bias)[projection.ids], SIZE, SIZE, background)
    torch.testing.assert_close(affine(drawn["rgb"], torch.tensor(1), drawn["accumulation"], background), transformed["rgb"],
                               atol=1e-5, rtol=1e-5)


def test_a_view_of_another_exposure_is_fitted_better_with_the_affine_table(one_thread):
    """One training view's photo is a darker, lifted copy (0.7 x + 0.1, as another exposure): without the table the
    Gaussians' colours cannot match it and the others at once; with it, its transform takes the difference (26.9 dB
    without, 31.6 with, after 160 steps). The held-out views, drawn with no transform, are about as good (30.25 and
    30.02 dB): the rows are centred, so the Gaussians take the views' mean exposure, a little off the five views'
    own, where the L1 loss without the table had followed the five and left the odd one out."""
    truth = tiny_model()
    train_c2w, held_c2w = arc_cameras(6), arc_cameras(3, shift=0.05)
    photos, held = photos_of(truth, train_c2w), photos_of(truth, held_c2w)
    photos[0] = photos[0] * 0.7 + 0.1
    results = {}
    for name, appearance in (("plain", None), ("affine", ViewColourAffine())):
        model = tiny_model(appearance)
        with torch.no_grad():  # the same geometry, every colour grey: the colours are what is learnt
            model.gaussians.sh0.copy_(rgb_to_sh(torch.full((400, 3), 0.5))[:, None])
        fit(model, photos, train_c2w, steps=160)
        model.eval()
        with torch.no_grad():
            out = model.render_view(K, train_c2w[0], SIZE, SIZE)
            view0 = out["rgb"] if appearance is None else appearance(out["rgb"], torch.tensor(0), out["accumulation"], model.space.background)
            results[name] = (psnr(view0, photos[0]), sum(psnr(a, b) for a, b in zip(photos_of(model, held_c2w), held)) / len(held))
    (plain_view0, plain_held), (affine_view0, affine_held) = results["plain"], results["affine"]
    assert affine_view0 > plain_view0 + 2.0, results
    assert affine_held > plain_held - 0.5, results
    offset, _ = appearance.offset_and_bias(torch.tensor(0))
    assert float(offset.detach().diagonal().mean()) < -0.05  # the view's transform darkens, as its photo was darkened


# -- each photo's exposure and white balance ----------------------------------------------------------------------------


def test_the_gains_are_centred_a_colour_each_and_leave_the_background():
    exposure = ViewExposure()
    exposure.resize(4)
    rgb, accumulation = torch.rand(5, 6, 3), torch.rand(5, 6)
    background = torch.tensor([0.2, 0.5, 0.9])
    torch.testing.assert_close(exposure(rgb, torch.tensor(2), accumulation, background), rgb)  # zero rows: gain 1
    assert exposure(rgb, None) is rgb  # a held-out view: the photos' mean
    with torch.no_grad():
        exposure.rows.copy_(torch.tensor([[0.3, 0.1, 0.0], [0.0, 0.0, 0.0], [-0.2, 0.1, 0.4], [0.5, 0.5, 0.5]]))
    # zero-mean in the logarithm: the mean photo is drawn with gain 1
    torch.testing.assert_close(exposure.centred().mean(dim=0), torch.zeros(3), atol=1e-6, rtol=0)
    gain = (exposure.rows[2] - exposure.rows.mean(dim=0)).exp()
    torch.testing.assert_close(exposure(rgb, torch.tensor(2)), rgb * gain)
    # only what the scene drew is gained: the background, where the view is clear, stays as it is
    drawn = rgb - (1 - accumulation[..., None]) * background
    torch.testing.assert_close(exposure(rgb, torch.tensor(2), accumulation, background), drawn * gain + (1 - accumulation[..., None]) * background)
    # a ray batch: each ray its own photo's gains
    rays = torch.rand(3, 3)
    gains = torch.stack([(exposure.rows[i] - exposure.rows.mean(dim=0)).exp() for i in (0, 3, 0)])
    torch.testing.assert_close(exposure(rays, torch.tensor([0, 3, 0])), rays * gains)
    exposure(rays, torch.tensor([0, 3, 0])).sum().backward()
    assert exposure.rows.grad[0].abs().min() > 0 and exposure.rows.grad[1].abs().max() > 0  # the mean ties every row in
    with pytest.raises(ValueError, match="ViewExposure needs lr > 0"):
        ViewExposure(lr=0.0)


def test_photos_of_other_exposures_and_white_balance_are_learnt_as_their_gains(one_thread):
    """Two of six training photos were taken at other settings (one 0.7 times as bright, one warmer: red 1.25, blue
    0.8). With the gains, those two views are fitted (21.0 and 20.2 dB without, 33.7 and 30.2 with, after 240 steps),
    their learnt gains (against the mean photo) are the ones they were taken with, and the held-out views, drawn at
    the mean, are no worse than without (25.7 without, 27.6 with: the Gaussians no longer split the difference)."""
    truth = tiny_model()
    train_c2w, held_c2w = arc_cameras(6), arc_cameras(3, shift=0.05)
    photos, held = photos_of(truth, train_c2w), photos_of(truth, held_c2w)
    photos[0] = photos[0] * 0.7
    photos[3] = photos[3] * torch.tensor([1.25, 1.0, 0.8])
    results = {}
    for name, appearance in (("plain", None), ("gains", ViewExposure())):
        model = tiny_model(appearance)
        with torch.no_grad():
            model.gaussians.sh0.copy_(rgb_to_sh(torch.full((400, 3), 0.5))[:, None])
        fit(model, photos, train_c2w, steps=240)
        model.eval()
        with torch.no_grad():
            views = []
            for view in (0, 3):
                out = model.render_view(K, train_c2w[view], SIZE, SIZE)
                views.append(psnr(out["rgb"] if appearance is None else appearance(out["rgb"], torch.tensor(view), out["accumulation"],
                                                                                    model.space.background), photos[view]))
            results[name] = (views, sum(psnr(a, b) for a, b in zip(photos_of(model, held_c2w), held)) / len(held))
    (plain_views, plain_held), (gain_views, gain_held) = results["plain"], results["gains"]
    assert min(g - p for g, p in zip(gain_views, plain_views)) > 2.0, results
    assert gain_held > plain_held - 0.5, results
    gains = appearance.gains(torch.arange(6)).detach()
    # the photos' geometric mean brightness is the Gaussians': each gain against the four untouched photos' gain
    relative = gains / gains[[1, 2, 4, 5]].mean(dim=0)
    torch.testing.assert_close(relative[0], torch.full((3,), 0.7), atol=0.05, rtol=0)
    torch.testing.assert_close(relative[3], torch.tensor([1.25, 1.0, 0.8]), atol=0.06, rtol=0)


# -- camera refinement ------------------------------------------------------------------------------------------------


def test_a_perturbed_training_pose_is_corrected_and_held_out_views_keep_theirs(one_thread):
    truth = tiny_model()
    true_c2w = arc_cameras(6)
    photos = photos_of(truth, true_c2w)
    loaded = true_c2w.clone()  # view 1's pose as a capture might have it: turned by 0.022 rad, moved by 0.04
    loaded[1, :3, :3] = axis_angle_to_rotation_matrix(torch.tensor([[0.0, 0.02, 0.01]]))[0] @ loaded[1, :3, :3]
    loaded[1, :3, 3] += torch.tensor([0.03, -0.02, 0.02])
    model = tiny_model(refinement=CameraRefinement())
    fit(model, photos, loaded, steps=120)
    refinement = model.camera_refinement
    assert refinement.rows.grad is not None and refinement.rows.detach()[1].abs().min() > 0
    model.eval()
    with torch.no_grad():
        corrected = refinement.corrected_c2w(loaded[1:2], torch.tensor([1]))[0]
        as_loaded = model.render_view(K, loaded[1], SIZE, SIZE)["rgb"]
        as_corrected = model.render_view(K, corrected, SIZE, SIZE)["rgb"]
        # the corrected pose draws the view's photo (29 dB as loaded, 39 corrected) and turns towards the truth
        assert psnr(as_corrected, photos[1]) > psnr(as_loaded, photos[1]) + 5.0
        assert (corrected[:3, :3] - true_c2w[1, :3, :3]).norm() < 0.75 * (loaded[1, :3, :3] - true_c2w[1, :3, :3]).norm()
        # a held-out view (render_view, as validation, nerf-eval, nerf-render and the viewer draw) is not corrected
        held = arc_cameras(1, shift=0.1)[0]
        before = model.render_view(K, held, SIZE, SIZE)["rgb"]
        refinement.rows.zero_()
        torch.testing.assert_close(model.render_view(K, held, SIZE, SIZE)["rgb"], before, atol=0, rtol=0)


# -- configuration, optimiser groups, logs and checkpoints --------------------------------------------------------


def test_both_are_off_by_default_and_train_in_their_own_groups_logging_their_penalties(make_config, scene_cache, monkeypatch, tmp_path):
    from nerf_lightning.checkpoints import load_model, load_run_data

    monkeypatch.setenv("NERF_LIGHTNING_CACHE", str(scene_cache))
    plain_cfg = make_config(*QUICK, "trainer.max_steps=2", "data.val_every=null", "trainer.enable_model_summary=false",
                            run_dir=tmp_path / "plain")
    plain = instantiate(plain_cfg.model)
    assert plain.appearance is None and plain.camera_refinement is None and plain.per_view_tables() == {}
    assert not any("appearance" in key or "camera" in key for key in train(plain_cfg))
    # a run trained without a table cannot resume with it: its optimiser has no group for it
    with pytest.raises(ValueError, match="trained without model/appearance: a resumed run cannot add it"):
        train(make_config(*QUICK, "model/appearance=affine", "trainer.max_steps=4", f"ckpt_path={plain_cfg.paths.output_dir}/checkpoints/last.ckpt",
                          "data.val_every=null", run_dir=tmp_path / "resumed"))
    cfg = make_config(*QUICK, "model/appearance=affine", "model/camera_refinement=so3xr3", "trainer.max_steps=4",
                      "data.val_every=4", "trainer.enable_model_summary=false")
    metrics = train(cfg)
    assert {"train/loss_appearance", "train/loss_camera_rotation", "train/loss_camera_translation", "val/psnr"} <= metrics.keys()
    model, info = load_model(cfg.paths.output_dir + "/checkpoints/last.ckpt")
    n_train = len(load_run_data(info["config"]).scene.train)
    assert isinstance(model.appearance, ViewColourAffine) and isinstance(model.camera_refinement, CameraRefinement)
    assert model.appearance.rows.shape == (n_train, 12) and model.camera_refinement.rows.shape == (n_train, 6)
    assert model.appearance.rows.abs().sum() > 0 and model.camera_refinement.rows.abs().sum() > 0  # learnt
    groups = {group["name"]: group for group in model.configure_optimizers()["optimizer"].param_groups}
    assert groups["appearance"]["lr"] == 2e-3 and groups["appearance"]["params"] == [model.appearance.rows]
    assert groups["camera_refinement"]["lr"] == 6e-4 and groups["camera_refinement"]["params"] == [model.camera_refinement.rows]


def test_a_splat_checkpoint_without_the_tables_loads_with_them_off_and_on(make_config):
    """A checkpoint's state from before the tables (or trained without them) loads into a model built without them,
    and into one built with them (whose tables stay as built: no correction); one with tables loads at its size."""
    old = instantiate(make_config(*QUICK).model)
    old.gaussians.initialise(torch.randn(50, 3), torch.rand(50, 3))
    saved = {"state_dict": {key: value.clone() for key, value in old.state_dict().items()}, "scene_space": old.space.state()}
    assert not any("appearance" in key or "camera_refinement" in key for key in saved["state_dict"])
    for overrides in ([], ["model/appearance=affine", "model/camera_refinement=so3xr3"]):
        model = instantiate(make_config(*QUICK, *overrides).model)
        checkpoint = {"state_dict": dict(saved["state_dict"]), "scene_space": saved["scene_space"]}
        model.on_load_checkpoint(checkpoint)
        model.load_state_dict(checkpoint["state_dict"])
        torch.testing.assert_close(model.gaussians.means, old.gaussians.means)
        assert model.render_view(K, arc_cameras(1)[0], SIZE, SIZE) is not None

    trained = instantiate(make_config(*QUICK, "model/appearance=affine", "model/camera_refinement=so3xr3").model)
    trained.gaussians.initialise(torch.randn(50, 3), torch.rand(50, 3))
    for table in trained.per_view_tables().values():
        table.resize(5)
        with torch.no_grad():
            table.rows.normal_()
    checkpoint = {"state_dict": trained.state_dict(), "scene_space": trained.space.state()}
    fresh = instantiate(make_config(*QUICK, "model/appearance=affine", "model/camera_refinement=so3xr3").model)
    fresh.on_load_checkpoint(checkpoint)
    fresh.load_state_dict(checkpoint["state_dict"])
    torch.testing.assert_close(fresh.appearance.rows, trained.appearance.rows)
    torch.testing.assert_close(fresh.camera_refinement.rows, trained.camera_refinement.rows)
