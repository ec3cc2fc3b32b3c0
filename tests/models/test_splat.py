"""Gaussian splats trained for real on the procedural scene; densification keeping the optimiser in step; the start
from sparse points or at random; the refusals of data=rays and NDC."""

from __future__ import annotations

import dataclasses
import math

import lightning as L
import pytest
import torch

from nerf_lightning.models.splat import SplatModule
from nerf_lightning.splats.gaussians import PARAMETERS, Gaussians
from nerf_lightning.splats.projection import Projection
from nerf_lightning.splats.strategy import DefaultStrategy
from nerf_lightning.training import train

QUICK = ["experiment=splat_procedural", "data.scene.size=32", "trainer.enable_progress_bar=false",
         "model.start.random.count=3000", "data.val_views=2"]


def test_a_short_run_on_the_procedural_scene_passes_a_bar_well_above_its_mean_colour(make_config, scene_cache, monkeypatch):
    monkeypatch.setenv("NERF_LIGHTNING_CACHE", str(scene_cache))
    cfg = make_config(*QUICK, "trainer.max_steps=400", "data.val_every=400", "model.strategy.refine_start=100",
                      "model.strategy.refine_every=50", "model.strategy.refine_stop=350", "model.strategy.reset_every=10000")
    metrics = train(cfg)
    # the training views' mean colour scores 10.1 dB on the held-out views of this scene; 400 steps of splats about 19
    assert metrics["step"] == 400 and metrics["val/psnr"] > 17.0, metrics
    assert metrics["train/gaussians"] != 3000  # densification grew or pruned them


def gaussians_for(n: int) -> Gaussians:
    g = Gaussians(sh_degree=1)
    generator = torch.Generator().manual_seed(0)
    g.initialise(torch.randn(n, 3, generator=generator), torch.rand(n, 3, generator=generator), generator)
    return g


def test_a_refinement_keeps_every_optimiser_state_the_size_of_its_parameter():
    g = gaussians_for(200)
    with torch.no_grad():
        g.log_scales[:100] = math.log(0.001)  # small: these clone
        g.log_scales[100:] = math.log(0.5)  # large: these split
        g.opacity_logits[150:] = -8.0  # nearly transparent: these are pruned
    optimizer = torch.optim.Adam([getattr(g, name) for name in PARAMETERS], lr=1e-3)
    (sum(getattr(g, name).sum() for name in PARAMETERS)).backward()
    optimizer.step()

    def replace(owner, name, value, rows_from):
        from nerf_lightning.parameters.groups import replace_parameter

        return replace_parameter(owner, name, value, [optimizer], rows_from)

    strategy = DefaultStrategy(refine_start=0, refine_every=1, prune_scale3d=100.0)
    strategy.scene_scale = 1.0
    means2d = torch.zeros(200, 2, requires_grad=True)
    # screen gradients (in units of half a 2x2 image: as they are) over the 2e-4 threshold from index 20 on
    means2d.grad = torch.stack([torch.where(torch.arange(200) >= 20, 1e-3, 1e-5), torch.zeros(200)], dim=-1)
    projection = Projection(torch.arange(200), means2d, torch.zeros(200, 3), torch.zeros(200), torch.zeros(200), torch.zeros(200, 2))
    strategy.after_backward(g, projection, width=2, height=2)
    old_exp_avg = optimizer.state[g.means]["exp_avg"].clone()
    strategy.after_step(g, step=1, replace=replace)
    # 20 untouched, 80 cloned (+80), 100 split (-100 +200): 380, less the transparent ones (50 split into 100, pruned)
    assert len(g) == 20 + 80 + 80 + 100
    for name in PARAMETERS:
        parameter = getattr(g, name)
        assert parameter.shape[0] == len(g)
        state = optimizer.state[parameter]
        assert state["exp_avg"].shape == parameter.shape and state["exp_avg_sq"].shape == parameter.shape
        assert any(parameter is p for group in optimizer.param_groups for p in group["params"])
    # the 100 that stayed (20 plus the 80 clones' originals) kept their state, the new ones start at zero
    torch.testing.assert_close(optimizer.state[g.means]["exp_avg"][:100], old_exp_avg[:100])
    assert optimizer.state[g.means]["exp_avg"][100:].abs().max() == 0


def test_opacities_are_reset_with_their_optimiser_state():
    g = gaussians_for(10)
    with torch.no_grad():
        g.opacity_logits.fill_(3.0)
    optimizer = torch.optim.Adam([getattr(g, name) for name in PARAMETERS], lr=1e-3)
    (sum(getattr(g, name).sum() for name in PARAMETERS)).backward()
    optimizer.step()
    from nerf_lightning.parameters.groups import replace_parameter

    DefaultStrategy(reset_every=5).after_step(g, step=5, replace=lambda o, n, v, r: replace_parameter(o, n, v, [optimizer], r))
    assert float(torch.sigmoid(g.opacity_logits.detach()).max()) == pytest.approx(0.01, rel=1e-4)
    assert optimizer.state[g.opacity_logits]["exp_avg"].abs().max() == 0
    assert optimizer.state[g.means]["exp_avg"].abs().max() > 0


def test_a_view_without_gaussians_in_sight_is_drawn_as_background(make_config, scene_cache, monkeypatch):
    from hydra.utils import instantiate

    model = instantiate(make_config(*QUICK).model)
    model.gaussians.initialise(torch.tensor([[0.0, 0.0, -50.0]]), torch.ones(1, 3))
    K = torch.tensor([[40.0, 0, 16], [0, 40.0, 16], [0, 0, 1]])
    out = model.render_view(K, torch.eye(4), 32, 32)  # looking down +z: the one Gaussian is behind
    torch.testing.assert_close(out["rgb"], model.space.background.expand(32, 32, 3))
    assert out["accumulation"].abs().max() == 0


def test_a_view_drawn_to_look_at_is_the_view_drawn_to_train(make_config):
    """render_view (no gradients: the fused numba projection where tiles draw) against draw with gradients (the
    PyTorch projection and SH), on Gaussians of every SH degree's coefficients."""
    from hydra.utils import instantiate

    model = instantiate(make_config(*QUICK, "model.gaussians.sh_degree=3").model).eval()  # eval: all three bands
    generator = torch.Generator().manual_seed(3)
    model.gaussians.initialise(torch.randn(500, 3, generator=generator) * 0.4, torch.rand(500, 3, generator=generator), generator)
    with torch.no_grad():
        model.gaussians.shN.normal_(0.0, 0.2, generator=generator)
    K = torch.tensor([[40.0, 0, 16], [0, 40.0, 12], [0, 0, 1]])
    c2w = torch.eye(4)
    c2w[2, 3] = -3.0
    assert model.sh_degree() == 3
    looked_at = model.render_view(K, c2w, 24, 32)
    trained, _ = model.draw(K, c2w, 24, 32)
    assert looked_at["accumulation"].mean() > 0.2  # the Gaussians are in sight
    for key in ("rgb", "depth", "accumulation"):
        torch.testing.assert_close(looked_at[key], trained[key].detach(), atol=1e-5, rtol=1e-5, msg=key)


def test_splats_refuse_rays_and_a_contracted_space_by_name(make_config, scene_cache, monkeypatch):
    monkeypatch.setenv("NERF_LIGHTNING_CACHE", str(scene_cache))
    with pytest.raises(ValueError, match="Gaussian splats train on whole views or patches: use data=views"):
        train(make_config("experiment=splat_procedural", "data=rays", "trainer.max_steps=1", "trainer.enable_progress_bar=false"))
    with pytest.raises(ValueError, match="data.ndc and data.contract must be false"):
        train(make_config(*QUICK, "data.contract=true", "trainer.max_steps=1"))


def test_a_gaussian_cap_over_the_machines_memory_is_refused_naming_the_cap(make_config, scene_cache, monkeypatch):
    monkeypatch.setenv("NERF_LIGHTNING_CACHE", str(scene_cache))
    with pytest.raises(ValueError, match=r"model.strategy.max_count \(or cap_max\) = 100000000000 Gaussians would take about"):
        train(make_config(*QUICK, "model.strategy.max_count=100000000000", "trainer.max_steps=1"))
    with pytest.raises(ValueError, match=r"model.strategy.max_count \(or cap_max\) = 100000000000 Gaussians"):
        train(make_config(*QUICK, "model/strategy=mcmc", "model.strategy.cap_max=100000000000", "model.strategy.max_count=null",
                          "trainer.max_steps=1"))



def test_the_start_scale_is_a_multiple_of_the_nearest_neighbours_distance():
    positions = torch.tensor([[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [0.0, 2.0, 0.0], [0.0, 0.0, 3.0], [10.0, 10.0, 10.0]])
    full, smaller = Gaussians(sh_degree=0), Gaussians(sh_degree=0, initial_scale=0.25)
    full.initialise(positions, torch.rand(5, 3))
    smaller.initialise(positions, torch.rand(5, 3))
    assert float(full.log_scales[0, 0]) == pytest.approx(math.log(2.0))  # (1 + 2 + 3) / 3
    torch.testing.assert_close(smaller.log_scales.detach(), full.log_scales.detach() + math.log(0.25))
    # a start of its own scale (the random start's scale) instead of initial_scale
    full.initialise(positions, torch.rand(5, 3), scale=0.25)
    torch.testing.assert_close(full.log_scales.detach(), smaller.log_scales.detach())
    with pytest.raises(ValueError, match="initial_scale must be > 0"):
        Gaussians(initial_scale=0.0)
    with pytest.raises(ValueError, match="start scale must be > 0"):
        full.initialise(positions, torch.rand(5, 3), scale=-1.0)


def test_sparse_points_start_at_initial_scale_and_a_random_start_at_its_scale(procedural_scene, make_config):
    from hydra.errors import InstantiationException
    from hydra.utils import instantiate

    from nerf_lightning.data.points import SparsePoints

    cfg = make_config("experiment=splat_360_cpu", "model/start=points", "model.start.random.count=200")
    assert cfg.model.start.random.scale == 0.15 and cfg.model.gaussians.initial_scale == 1.0
    random_start = instantiate(cfg.model)
    random_start.start(random_start.gaussians, procedural_scene)
    unscaled = instantiate(make_config("experiment=splat_360_cpu", "model/start=points", "model.start.random.count=200",
                                       "model.start.random.scale=null").model)
    unscaled.start(unscaled.gaussians, procedural_scene)  # the same seeded points, at initial_scale
    torch.testing.assert_close(random_start.gaussians.log_scales.detach(),
                               unscaled.gaussians.log_scales.detach() + math.log(0.15))
    points = SparsePoints(random_start.gaussians.means.detach().clone(), torch.full((200, 3), 128, dtype=torch.uint8))
    from_points = instantiate(cfg.model)
    from_points.start(from_points.gaussians, dataclasses.replace(procedural_scene, points=points))
    torch.testing.assert_close(from_points.gaussians.log_scales.detach(), unscaled.gaussians.log_scales.detach())
    with pytest.raises(InstantiationException, match="model.start.random.scale must be > 0"):
        instantiate(make_config("experiment=splat_360_cpu", "model.start.random.scale=0").model)
    # random points beside the sparse ones: the points first, at initial_scale, then the random ones at their scale
    beside = instantiate(make_config("experiment=splat_360_cpu", "model.start.random.count=200", "model.start.beside=50").model)
    beside.start(beside.gaussians, dataclasses.replace(procedural_scene, points=points))
    means = beside.gaussians.means.detach()
    assert len(means) == 250
    torch.testing.assert_close(means[:200], points.positions)
    together = Gaussians(sh_degree=0)
    together.initialise(means, torch.rand(250, 3))  # the union's neighbour distances, at 1
    torch.testing.assert_close(beside.gaussians.log_scales.detach()[:200], together.log_scales.detach()[:200])
    torch.testing.assert_close(beside.gaussians.log_scales.detach()[200:], together.log_scales.detach()[200:] + math.log(0.15))
    with pytest.raises(InstantiationException, match="model.start.beside must be an integer >= 0"):
        instantiate(make_config("experiment=splat_360_cpu", "model.start.beside=-1").model)


def test_a_capture_with_sparse_points_starts_its_gaussians_there_and_trains(procedural_scene, make_config, tmp_path, caplog):
    """A transforms.json capture naming its sparse points (as nerf-process-data writes it): one Gaussian a point, at
    the point in the scene's world, of the point's colour; said once in the log; then it trains."""
    import json
    import logging

    from hydra.utils import instantiate

    from nerf_lightning.capture.output import write_points_ply
    from nerf_lightning.data.formats import load_transforms
    from nerf_lightning.splats.sh import SH_C0
    from tests.data.test_points import surface_points
    from tests.data.test_transforms import write_transforms

    views = procedural_scene.train.subset(list(range(8)))
    root = write_transforms(views, tmp_path / "capture")
    points, colours = surface_points(views)
    write_points_ply(root / "sparse_pc.ply", points, colours)
    meta = json.loads((root / "transforms.json").read_text())
    (root / "transforms.json").write_text(json.dumps({**meta, "ply_file_path": "sparse_pc.ply"}))
    scene = load_transforms(root, holdout_every=4)

    cfg = make_config("experiment=splat_360_cpu", f"data.root={root}", "data.scene.downscale=1", "trainer.max_steps=3",
                      "data.val_every=null", "trainer.enable_progress_bar=false")
    model = instantiate(cfg.model)
    with caplog.at_level(logging.INFO, logger="nerf_lightning.models.splat_start"):
        model.start(model.gaussians, scene)
    assert "Gaussians start from the capture's 300 sparse points" in caplog.text and "no sparse points" not in caplog.text
    torch.testing.assert_close(model.gaussians.means.detach(), scene.points.positions)
    torch.testing.assert_close(0.5 + SH_C0 * model.gaussians.sh0.detach()[:, 0], scene.points.colours.float() / 255.0, atol=1e-6, rtol=0)
    metrics = train(cfg)
    assert metrics["step"] == 3 and metrics["train/gaussians"] == 300
    # refining from the first step: the preset's near-camera pruning asks the training cameras, which the model
    # gives the strategy when training starts (without them the first refinement would stop with an error)
    refined = make_config("experiment=splat_360_cpu", f"data.root={root}", "data.scene.downscale=1", "trainer.max_steps=3",
                          "data.val_every=null", "trainer.enable_progress_bar=false", "model.strategy.refine_start=1",
                          "model.strategy.refine_every=1", f"paths.output_dir={tmp_path / 'refined'}")
    assert refined.model.strategy.prune_near_cameras == 0.6
    assert train(refined)["step"] == 3



def test_an_exclude_mask_keeps_the_pixels_outside_it_out_of_the_loss(make_config, scene_cache, monkeypatch):
    from types import SimpleNamespace

    from hydra.utils import instantiate

    monkeypatch.setenv("NERF_LIGHTNING_CACHE", str(scene_cache))
    model = instantiate(make_config(*QUICK).model)
    model.log = lambda *args, **kwargs: None
    rendered = torch.rand(32, 32, 3, requires_grad=True)  # what the splats drew, standing in for the rasteriser
    model.draw = lambda K, c2w, height, width, background=None, depth=True: ({"rgb": rendered}, SimpleNamespace(means2d=torch.zeros(1, 2)))
    mask = torch.zeros(32, 32, dtype=torch.bool)
    mask[8:24, 8:24] = True
    model.training_step({"image": torch.rand(32, 32, 3), "K": None, "c2w": None, "loss_mask": mask}, 0).backward()
    assert rendered.grad[~mask].abs().max() == 0 and rendered.grad[mask].abs().min() > 0
    rendered.grad = None
    model.training_step({"image": torch.rand(32, 32, 3), "K": None, "c2w": None}, 0).backward()  # no mask: every pixel
    assert rendered.grad.abs().min() > 0


@pytest.mark.parametrize("train_background", ["scene", "random"])
def test_a_random_training_background_is_behind_the_gaussians_and_outside_the_object(make_config, scene_cache, monkeypatch, train_background):
    from types import SimpleNamespace

    from hydra.errors import InstantiationException
    from hydra.utils import instantiate

    monkeypatch.setenv("NERF_LIGHTNING_CACHE", str(scene_cache))
    model = instantiate(make_config(*QUICK, f"model.loss.train_background={train_background}").model)
    model.log = lambda *args, **kwargs: None
    drawn_over = []

    def draw(K, c2w, height, width, background=None, depth=True):
        drawn_over.append(background)
        return {"rgb": torch.full((32, 32, 3), 0.5, requires_grad=True)}, SimpleNamespace(means2d=torch.zeros(1, 2))

    model.draw = draw
    seen = []
    model.photometric_loss = lambda rgb, image, mask: seen.append(image) or ((rgb - image).abs().mean(), None)
    mask = torch.zeros(32, 32, dtype=torch.bool)
    mask[8:24, 8:24] = True
    image = torch.rand(32, 32, 3) * mask[..., None]  # the object over black, as data.masks=background gives it
    for _ in range(2):
        model.training_step({"image": image, "K": None, "c2w": None, "object_mask": mask}, 0)
    if train_background == "scene":  # the scene's colour behind the Gaussians, the photo as it is
        assert drawn_over == [None, None] and all(torch.equal(target, image) for target in seen)
    else:  # a colour a step, drawn behind the Gaussians and put outside the object, the object as it is
        assert not torch.equal(drawn_over[0], drawn_over[1])
        for colour, target in zip(drawn_over, seen):
            assert torch.equal(target[mask], image[mask]) and torch.equal(target[~mask], colour.expand(int((~mask).sum()), 3))
    with pytest.raises(InstantiationException, match="model.loss.train_background must be one of scene, random, got 'noise'"):
        instantiate(make_config(*QUICK, "model.loss.train_background=noise").model)


def test_the_mask_loss_teaches_the_gaussians_opacity_from_the_masks(make_config, scene_cache, monkeypatch):
    from types import SimpleNamespace

    from hydra.utils import instantiate

    monkeypatch.setenv("NERF_LIGHTNING_CACHE", str(scene_cache))
    model = instantiate(make_config(*QUICK, "model.loss.mask_loss=0.5").model)
    model.log = lambda *args, **kwargs: None
    mask = torch.zeros(32, 32, dtype=torch.bool)
    mask[8:24, 8:24] = True
    image = torch.zeros(32, 32, 3)  # a black object over the black background: the colours cannot tell them apart
    accumulation = torch.full((32, 32), 0.5, requires_grad=True)
    model.draw = lambda K, c2w, height, width, background=None, depth=True: (
        {"rgb": torch.zeros(32, 32, 3, requires_grad=True), "accumulation": accumulation}, SimpleNamespace(means2d=torch.zeros(1, 2)))
    model.loss = dataclasses.replace(model.loss, ssim_weight=0.0)  # the L1 alone
    loss = model.training_step({"image": image, "K": None, "c2w": None, "object_mask": mask}, 0)
    assert float(loss) == pytest.approx(0.5 * math.log(2.0), rel=1e-4)  # the colours match: all of it is the masks'
    loss.backward()
    assert (accumulation.grad[mask] < 0).all() and (accumulation.grad[~mask] > 0).all()  # opaque on the object, clear off it
    with pytest.raises(ValueError, match="model.loss.mask_loss > 0 needs the object's masks .* data.masks=background"):
        model.training_step({"image": image, "K": None, "c2w": None}, 0)


def test_splats_train_and_draw_on_the_cpus_tiles_where_auto_would_pick_an_apple_gpu(make_config, scene_cache, monkeypatch, caplog):
    from omegaconf import OmegaConf

    from nerf_lightning.checkpoints import load_model
    from nerf_lightning.models.radiance_field import RadianceFieldModule
    from nerf_lightning.models.splat import SplatModule
    from nerf_lightning.splats.draw import device_for_splats
    from nerf_lightning.training.run import accelerator_for

    monkeypatch.setenv("NERF_LIGHTNING_CACHE", str(scene_cache))
    cfg = make_config(*QUICK, "trainer.max_steps=2", "data.val_every=null", "trainer.enable_model_summary=false")
    train(cfg)  # on this machine's CPU, before the Apple GPU is faked
    monkeypatch.setattr(torch.backends.mps, "is_available", lambda: True)  # a Mac: auto is its Apple GPU
    monkeypatch.setattr(torch.cuda, "is_available", lambda: False)
    with caplog.at_level("WARNING", logger="nerf_lightning.splats.draw"):
        assert device_for_splats("mps", asked=False) == torch.device("cpu")
    assert sum("not this Apple GPU" in record.getMessage() for record in caplog.records) == 1
    assert device_for_splats("mps", asked=True) == torch.device("mps")  # asked for by name: it gets it
    assert device_for_splats("cuda", asked=False) == torch.device("cuda")
    # training: auto becomes the CPU for splats, not for a NeRF; an accelerator named stays
    model = SplatModule(gaussians=Gaussians(sh_degree=0), optimizer=torch.optim.Adam, learning_rates=dict.fromkeys(PARAMETERS, 1e-3))
    assert accelerator_for(cfg, model) == {"accelerator": "cpu", "devices": 1}
    assert accelerator_for(OmegaConf.merge(cfg, {"trainer": {"accelerator": "mps"}}), model) == {}
    assert accelerator_for(cfg, object.__new__(RadianceFieldModule)) == {}
    # the commands: device=auto loads the splats on the CPU
    loaded, _ = load_model(f"{cfg.paths.output_dir}/checkpoints/last.ckpt", device="auto")
    assert loaded.device.type == "cpu"


class StopAtThree(L.Callback):
    """Stops the run after its third step, as a time limit would."""

    def on_train_batch_end(self, trainer, pl_module, outputs, batch, batch_idx):
        if trainer.global_step == 3:
            trainer.should_stop = True


def test_the_step_figures_are_logged_when_the_logger_writes_and_at_an_early_stop(make_config, scene_cache, monkeypatch):
    monkeypatch.setenv("NERF_LIGHTNING_CACHE", str(scene_cache))
    logged = []
    original = SplatModule.log_step_figures

    def spy(self):
        logged.append((self.global_step, self._step_logged is not None))
        original(self)

    monkeypatch.setattr(SplatModule, "log_step_figures", spy)
    cfg = make_config(*QUICK, "trainer.max_steps=20", "trainer.log_every_n_steps=2", "data.val_every=null",
                      "trainer.enable_model_summary=false", f"+callbacks.stop._target_={__name__}.StopAtThree")
    metrics = train(cfg)
    assert metrics["step"] == 3 and math.isfinite(metrics["train/psnr"]) and metrics["train/gaussians"] == 3000
    # the steps the logger writes (steps 2: global_step 1 during it), and the stop after step 3 (global_step 3 by then)
    assert [step for step, fresh in logged if fresh] == [1, 3], logged
