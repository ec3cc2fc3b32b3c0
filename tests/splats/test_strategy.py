"""The MCMC strategy (3DGS as Markov chain Monte Carlo): relocation keeps the count and what the views see, growth
stays under the cap, the optimiser's state follows the edits, the noise moves only the transparent, and a short run
on the procedural scene learns with it."""

from __future__ import annotations

import math

import lightning as L
import pytest
import torch

from nerf_lightning.parameters.groups import replace_parameter
from nerf_lightning.splats.gaussians import PARAMETERS
from nerf_lightning.splats.projection import Projection, views_seeing
from nerf_lightning.splats.mcmc import MCMCStrategy, relocation
from nerf_lightning.splats.strategy import DefaultStrategy
from nerf_lightning.training import train
from tests.models.test_splat import QUICK, gaussians_for


def stepped_optimizer(g):
    """Adam over every parameter, stepped once so that its state is not zero."""
    optimizer = torch.optim.Adam([getattr(g, name) for name in PARAMETERS], lr=1e-3)
    (sum((getattr(g, name) ** 2).sum() for name in PARAMETERS)).backward()
    optimizer.step()
    optimizer.zero_grad(set_to_none=True)
    return optimizer, lambda owner, name, value, rows_from: replace_parameter(owner, name, value, [optimizer], rows_from)


def scale_share(opacity: float, copies: int) -> float:
    """The factor of the scales by the paper's eq. 9 as gsplat's kernel writes it (the double sum), in Python floats."""
    shared = 1.0 - (1.0 - opacity) ** (1.0 / copies)
    total = sum(math.comb(i - 1, k) * (-1) ** k * shared ** (k + 1) / math.sqrt(k + 1) for i in range(1, copies + 1) for k in range(i))
    return opacity / total


def test_relocation_moves_the_dead_onto_the_live_and_they_render_as_the_source_did():
    g = gaussians_for(200)
    with torch.no_grad():
        g.opacity_logits[:] = torch.logit(torch.linspace(0.2, 0.9, 200))
        g.opacity_logits[::4] = -8.0  # 50 dead
    optimizer, replace = stepped_optimizer(g)
    before = {name: getattr(g, name).detach().clone() for name in PARAMETERS}
    dead = torch.sigmoid(before["opacity_logits"]) < 0.005
    old_state = {name: optimizer.state[getattr(g, name)]["exp_avg"].clone() for name in PARAMETERS}

    assert MCMCStrategy().relocate(g, replace) == 50
    assert len(g) == 200
    after = {name: getattr(g, name).detach() for name in PARAMETERS}
    # every dead row is now a copy of a live row (the same mean, rotation, colour, and the shared opacity and scales)
    sources = []
    for row in torch.nonzero(dead).squeeze(1).tolist():
        same = (after["means"] == after["means"][row]).all(dim=-1) & ~dead
        assert int(same.sum()) == 1, row
        source = int(torch.nonzero(same)[0])
        for name in PARAMETERS:
            torch.testing.assert_close(after[name][row], after[name][source], rtol=0, atol=0)
        sources.append(source)
    assert float(torch.sigmoid(after["opacity_logits"]).min()) >= 0.005
    # a source drawn k times and its k copies: 1 - (1 - o')^(k + 1) = o, and the scales shared as eq. 9 says
    for source in set(sources):
        copies = sources.count(source) + 1
        opacity = float(torch.sigmoid(before["opacity_logits"][source]))
        shared = float(torch.sigmoid(after["opacity_logits"][source]))
        assert 1.0 - (1.0 - shared) ** copies == pytest.approx(opacity, rel=1e-5)
        torch.testing.assert_close(after["log_scales"][source], before["log_scales"][source] + math.log(scale_share(opacity, copies)))
    # the rows it did not touch are as they were, their optimiser state too; the touched rows' state is zero
    touched = dead.clone()
    touched[sources] = True
    for name in PARAMETERS:
        torch.testing.assert_close(after[name][~touched], before[name][~touched], rtol=0, atol=0)
        state = optimizer.state[getattr(g, name)]
        assert state["exp_avg"].shape == getattr(g, name).shape
        assert state["exp_avg"][touched].abs().max() == 0 and state["exp_avg_sq"][touched].abs().max() == 0
        torch.testing.assert_close(state["exp_avg"][~touched], old_state[name][~touched])


def test_the_shared_opacity_and_scales_match_the_papers_formula():
    opacities = torch.tensor([0.01, 0.3, 0.5, 0.9, 0.999, 0.5])
    copies = torch.tensor([2, 3, 1, 10, 51, 80])  # more than 51 copies are shared as 51
    shared, scales = relocation(opacities, torch.ones(6, 3), copies)
    for index, (opacity, n) in enumerate(zip(opacities.tolist(), [2, 3, 1, 10, 51, 51])):
        assert 1.0 - (1.0 - float(shared[index])) ** n == pytest.approx(opacity, rel=1e-5)
        assert float(scales[index, 0]) == pytest.approx(scale_share(opacity, n), rel=1e-4)
    assert scales[2].tolist() == [1.0, 1.0, 1.0]  # one copy: the Gaussian itself


def test_growth_adds_at_most_five_percent_and_never_passes_the_cap():
    g = gaussians_for(100)
    _, replace = stepped_optimizer(g)
    strategy = MCMCStrategy(cap_max=112)
    assert strategy.grow(g, replace) == 5 and len(g) == 105
    assert strategy.grow(g, replace) == 5 and len(g) == 110
    assert strategy.grow(g, replace) == 2 and len(g) == 112  # 5% would pass the cap
    assert strategy.grow(g, replace) == 0 and len(g) == 112
    # an experiment's max_count (the default strategy's cap) caps it too
    assert MCMCStrategy(cap_max=1000, max_count=500, reset_every=100).cap_max == 500


def test_a_refinement_keeps_every_optimiser_state_the_size_of_its_parameter():
    g = gaussians_for(200)
    with torch.no_grad():
        g.opacity_logits[150:] = -8.0  # 50 dead
    optimizer, replace = stepped_optimizer(g)
    strategy = MCMCStrategy(refine_start=100, refine_every=100)
    strategy.after_step(g, step=50, replace=replace, means_lr=0.0)  # not yet time
    assert len(g) == 200 and float(torch.sigmoid(g.opacity_logits.detach()).min()) < 0.005
    strategy.after_step(g, step=100, replace=replace, means_lr=0.0)
    assert len(g) == 210 and float(torch.sigmoid(g.opacity_logits.detach()).min()) >= 0.005
    for name in PARAMETERS:
        parameter = getattr(g, name)
        state = optimizer.state[parameter]
        assert state["exp_avg"].shape == parameter.shape and state["exp_avg_sq"].shape == parameter.shape
        assert any(parameter is p for group in optimizer.param_groups for p in group["params"])
        assert state["exp_avg"][150:].abs().max() == 0  # the relocated rows and the added ones start afresh


def test_the_noise_moves_transparent_gaussians_and_leaves_opaque_ones():
    g = gaussians_for(200)
    with torch.no_grad():
        g.log_scales.fill_(math.log(0.1))
        g.opacity_logits[:100] = torch.logit(torch.tensor(0.001))
        g.opacity_logits[100:] = torch.logit(torch.tensor(0.9))
    before = g.means.detach().clone()
    parameter = g.means
    MCMCStrategy().after_step(g, step=1, replace=None, means_lr=1.6e-4)  # step 1: no refinement, only noise
    moved = (g.means.detach() - before).norm(dim=-1)
    assert g.means is parameter  # in place: the optimiser keeps the parameter
    # noise 0.01 (the covariance) x 1.6e-4 x 5e5 x 0.6 (the gate at 0.001) a coordinate: about 0.8 for the transparent
    assert 0.3 < float(moved[:100].mean()) < 3.0
    assert float(moved[100:].max()) < 1e-6
    now = g.means.detach().clone()
    MCMCStrategy().after_step(g, step=1, replace=None, means_lr=0.0)  # no learning rate: no noise
    assert torch.equal(g.means.detach(), now)


def test_the_regulariser_is_the_mean_opacity_and_scale_and_the_default_strategy_has_none():
    g = gaussians_for(50)
    loss = MCMCStrategy(opacity_reg=0.01, scale_reg=0.02).loss(g)
    expected = 0.01 * torch.sigmoid(g.opacity_logits).mean() + 0.02 * torch.exp(g.log_scales).mean()
    torch.testing.assert_close(loss, expected)
    assert loss.requires_grad
    assert MCMCStrategy(opacity_reg=0.0, scale_reg=0.0).loss(g) is None
    assert DefaultStrategy().loss(g) is None


class FirstStepPSNR(L.Callback):
    """Keeps train/psnr after the first step (the starting cloud's, near enough; logged at the steps the logger writes)."""

    values: list[float] = []

    def on_train_batch_end(self, trainer, pl_module, outputs, batch, batch_idx):
        if trainer.global_step == 1:
            FirstStepPSNR.values.append(float(trainer.callback_metrics["train/psnr"]))


def test_a_short_mcmc_run_on_the_procedural_scene_learns_and_keeps_under_the_cap(make_config, scene_cache, monkeypatch):
    monkeypatch.setenv("NERF_LIGHTNING_CACHE", str(scene_cache))
    monkeypatch.setattr(FirstStepPSNR, "values", [])
    # refinements at 40, 80, 120, 160: 3000 -> 3150 -> 3300 (the cap), then relocation only
    cfg = make_config(*QUICK, "model/strategy=mcmc", "trainer.max_steps=240", "trainer.log_every_n_steps=1", "data.val_every=240", "model.strategy.refine_start=40",
                      "model.strategy.refine_every=40", "model.strategy.refine_stop=200", "model.strategy.cap_max=3300",
                      f"+callbacks.first_step_psnr._target_={__name__}.FirstStepPSNR")
    metrics = train(cfg)
    # the first step scores about 9 dB; 240 steps about 17 on the held-out views
    assert len(FirstStepPSNR.values) == 1 and FirstStepPSNR.values[0] < 11.0, FirstStepPSNR.values
    assert metrics["step"] == 240 and metrics["val/psnr"] > FirstStepPSNR.values[0] + 5.0, metrics
    assert metrics["train/gaussians"] == 3300


@pytest.mark.parametrize(("prune_large_after", "step", "pruned"), [(None, 200, False), (None, 400, True), (100, 200, True)])
def test_large_gaussians_are_pruned_only_after_prune_large_after_or_the_first_reset(prune_large_after, step, pruned):
    g = gaussians_for(100)
    with torch.no_grad():
        g.log_scales[:] = math.log(0.01)
        g.log_scales[:10] = math.log(0.5)  # over prune_scale3d (0.1) of the scene scale (1)
        g.opacity_logits[:] = 2.0  # opaque: none goes for its opacity
    optimizer, replace = stepped_optimizer(g)
    strategy = DefaultStrategy(refine_start=0, refine_every=100, reset_every=300, prune_large_after=prune_large_after)
    means2d = torch.zeros(100, 2, requires_grad=True)
    means2d.grad = torch.zeros(100, 2)  # no gradient: nothing grows
    strategy.after_backward(g, Projection(torch.arange(100), means2d, torch.zeros(100, 3), torch.zeros(100), torch.zeros(100),
                                          torch.zeros(100, 2)), width=2, height=2)
    strategy.after_step(g, step=step, replace=replace, means_lr=0.0)
    assert len(g) == (90 if pruned else 100)
    assert float(torch.exp(g.log_scales.detach()).amax()) == pytest.approx(0.01 if pruned else 0.5, rel=1e-2)


def ring_of_cameras(count: int = 12, radius: float = 2.0):
    """``count`` 64x64 cameras (focal 64) on a circle in the xy plane, each looking at the origin (OpenCV axes)."""
    c2ws = []
    for angle in torch.arange(count) * (2 * math.pi / count):
        centre = torch.tensor([radius * math.cos(angle), radius * math.sin(angle), 0.0])
        forward = -centre / centre.norm()
        down = torch.tensor([0.0, 0.0, -1.0])
        right = torch.linalg.cross(down, forward)
        c2w = torch.eye(4)
        c2w[:3, 0], c2w[:3, 1], c2w[:3, 2], c2w[:3, 3] = right, down, forward, centre
        c2ws.append(c2w)
    K = torch.tensor([[64.0, 0.0, 32.0], [0.0, 64.0, 32.0], [0.0, 0.0, 1.0]]).expand(count, 3, 3)
    return K, torch.stack(c2ws)


def test_views_seeing_counts_the_cameras_a_point_falls_in_front_of_and_inside():
    K, c2w = ring_of_cameras()
    centre0 = c2w[0, :3, 3]
    points = torch.stack([torch.zeros(3), 0.9 * centre0, 1.5 * centre0, torch.tensor([0.0, 0.0, 5.0])])
    counts = views_seeing(points, K, c2w, 64, 64)
    # the origin: every camera; just in front of camera 0: camera 0 and the three across the ring that face it (off
    # the images of the others); behind camera 0: not camera 0; far above the ring: off every image
    assert counts[0] == 12 and counts[1] == 4 and counts[3] == 0
    assert views_seeing(points[2:3], K[:1], c2w[:1], 64, 64) == 0 and views_seeing(points[1:2], K[:1], c2w[:1], 64, 64) == 1


@pytest.mark.parametrize("prune_near_cameras", [None, 0.6])
def test_gaussians_near_a_camera_that_few_views_see_are_pruned(prune_near_cameras):
    K, c2w = ring_of_cameras()
    centre0 = c2w[0, :3, 3]
    g = gaussians_for(3)
    with torch.no_grad():
        # the subject at the origin; a floater just in front of camera 0; one far out behind the subject, which few
        # views see but no camera is near
        g.means[:] = torch.stack([torch.zeros(3), 0.85 * centre0, torch.tensor([0.0, 0.0, 0.3]) - 2.5 * centre0])
        g.log_scales[:] = math.log(0.01)
        g.opacity_logits[:] = 2.0
    optimizer, replace = stepped_optimizer(g)
    strategy = DefaultStrategy(refine_start=0, refine_every=100, prune_near_cameras=prune_near_cameras)
    strategy.scene_scale = 1.1 * 2.0
    strategy.cameras = (K, c2w, 64, 64)
    assert int(views_seeing(g.means.detach()[2:], K, c2w, 64, 64)) < 5  # few see the far one too
    means2d = torch.zeros(3, 2, requires_grad=True)
    means2d.grad = torch.zeros(3, 2)  # nothing grows
    strategy.after_backward(g, Projection(torch.arange(3), means2d, torch.zeros(3, 3), torch.zeros(3), torch.zeros(3),
                                          torch.zeros(3, 2)), width=64, height=64)
    strategy.after_step(g, step=100, replace=replace, means_lr=0.0)
    expected = [0, 2] if prune_near_cameras else [0, 1, 2]
    assert len(g) == len(expected)
    kept = torch.stack([torch.zeros(3), 0.85 * centre0, torch.tensor([0.0, 0.0, 0.3]) - 2.5 * centre0])[expected]
    assert torch.allclose(g.means.detach(), kept, atol=1e-2)  # (the optimiser stepped once before)


def test_pruning_near_cameras_without_the_cameras_is_one_clear_error():
    g = gaussians_for(3)
    optimizer, replace = stepped_optimizer(g)
    strategy = DefaultStrategy(refine_start=0, refine_every=100, prune_near_cameras=0.6)
    means2d = torch.zeros(3, 2, requires_grad=True)
    means2d.grad = torch.zeros(3, 2)
    strategy.after_backward(g, Projection(torch.arange(3), means2d, torch.zeros(3, 3), torch.zeros(3), torch.zeros(3),
                                          torch.zeros(3, 2)), width=64, height=64)
    with pytest.raises(ValueError, match="prune_near_cameras needs the training cameras"):
        strategy.after_step(g, step=100, replace=replace, means_lr=0.0)


def symmetric_footprint() -> Projection:
    """One round footprint in the middle of a 24 x 20 view, drawn symmetrically about its centre: by symmetry, the
    pixels' pulls on its centre cancel under a loss that treats them all alike."""
    means2d = torch.tensor([[12.0, 10.0]], requires_grad=True)
    conics = torch.tensor([[0.05, 0.0, 0.05]])
    return Projection(torch.arange(1), means2d, conics, torch.tensor([0.8]), torch.tensor([1.0]), torch.full((1, 2), 20.0))


@pytest.mark.parametrize("rasteriser", ["pairs", "tiles"])
def test_absgrad_grows_a_gaussian_whose_pixels_pull_its_centre_in_opposite_ways(rasteriser):
    from nerf_lightning.splats.draw import RASTERIZERS

    stats = {}
    for absgrad in (False, True):
        g = gaussians_for(1)
        with torch.no_grad():
            g.log_scales[:] = math.log(0.001)  # small: it grows by a clone
            g.opacity_logits[:] = 2.0
        optimizer, replace = stepped_optimizer(g)
        projection = symmetric_footprint()
        drawer = RASTERIZERS[rasteriser]().for_device("cpu")
        out = drawer.rasterize(projection, torch.tensor([[0.9, 0.5, 0.1]]), 20, 24, torch.zeros(3), absgrad=True)
        out["rgb"].sum().backward()  # too bright everywhere, alike: each pixel pulls the centre towards itself
        stats[absgrad] = (projection.means2d.grad.norm(), projection.means2d.absgrad.norm())
        net, total = stats[absgrad]
        assert net < 1e-3 * total  # the pulls cancel; their absolute values do not
        strategy = DefaultStrategy(refine_start=0, refine_every=100, grow_grad2d=float((net * total).sqrt() * 12), absgrad=absgrad)
        strategy.after_backward(g, projection, width=24, height=20)
        strategy.after_step(g, step=100, replace=replace, means_lr=0.0)
        assert len(g) == (2 if absgrad else 1), absgrad


def test_absgrad_from_a_view_drawn_without_it_is_one_clear_error():
    g = gaussians_for(1)
    projection = symmetric_footprint()
    projection.means2d.grad = torch.ones(1, 2)  # a gradient, as if drawn without absgrad=True
    with pytest.raises(RuntimeError, match="model.strategy.absgrad needs"):
        DefaultStrategy(absgrad=True).after_backward(g, projection, width=24, height=20)


def test_a_short_run_with_absgrad_grows_its_gaussians_by_it(make_config, scene_cache, monkeypatch):
    monkeypatch.setenv("NERF_LIGHTNING_CACHE", str(scene_cache))
    cfg = make_config(*QUICK, "trainer.max_steps=120", "data.val_every=120", "model.strategy.refine_start=40",
                      "model.strategy.refine_every=40", "model.strategy.refine_stop=100", "model.strategy.absgrad=true",
                      "model.strategy.grow_grad2d=8.0e-4")
    metrics = train(cfg)  # the model asked the rasteriser for absgrad: without it, after_backward would raise
    assert metrics["step"] == 120 and metrics["train/gaussians"] > 3000, metrics


def test_the_view_consistent_strategy_grows_where_the_views_agree_and_prunes_what_they_barely_draw():
    from nerf_lightning.splats.strategy import ViewConsistentStrategy

    g = gaussians_for(100)
    with torch.no_grad():
        g.log_scales[:] = math.log(0.001)  # small: a Gaussian that grows is cloned
        g.opacity_logits[:] = 2.0  # opaque: none goes for its opacity
    optimizer, replace = stepped_optimizer(g)
    strategy = ViewConsistentStrategy(refine_start=0, refine_every=100, grow_score=1.0, prune_drawn=0.01, views=3)
    strategy.cameras = (torch.eye(3).expand(5, 3, 3), torch.eye(4).expand(5, 4, 4), 8, 8)
    high, drawn, seen = torch.zeros(100), torch.full((100,), 5.0), torch.ones(100, dtype=torch.bool)
    high[:20] = 2.0  # the views agree these sit under their errors
    drawn[90:95] = 0.001  # seen, but drawing almost nothing: pruned
    seen[95:] = False
    drawn[95:] = 0.0  # never seen by the views drawn: kept
    asked = []
    strategy.score_views = lambda views, threshold: asked.append((views, threshold)) or (high, drawn, seen)
    means2d = torch.zeros(100, 2, requires_grad=True)
    means2d.grad = torch.zeros(100, 2)
    means2d.grad[:10] = 1.0  # a large gradient where the views agree, and where they do not (10 to 19 agree, no gradient)
    means2d.grad[30:40] = 1.0
    strategy.after_backward(g, Projection(torch.arange(100), means2d, torch.zeros(100, 3), torch.zeros(100), torch.zeros(100),
                                          torch.zeros(100, 2)), width=2, height=2)
    strategy.after_step(g, step=100, replace=replace, means_lr=0.0)
    (views, threshold), = asked
    assert len(views) == 3 and len(set(views.tolist())) == 3 and threshold == strategy.error_threshold
    assert len(g) == 100 + 10 - 5  # ten clones (0 to 9, not 30 to 39), five pruned
    with pytest.raises(ValueError, match="views >= 1"):
        ViewConsistentStrategy(views=0)


class KeepModule(L.Callback):
    """Keeps the trained module and its training views when training ends."""

    kept: dict = {}

    def on_train_end(self, trainer, pl_module):
        KeepModule.kept.update(module=pl_module, views=trainer.datamodule.scene.train)


def test_the_splat_models_view_scores_are_the_blend_weights_the_views_draw(make_config, scene_cache, monkeypatch):
    from nerf_lightning.data.image_stack import as_float_rgb

    monkeypatch.setenv("NERF_LIGHTNING_CACHE", str(scene_cache))
    monkeypatch.setattr(KeepModule, "kept", {})
    cfg = make_config(*QUICK, "model/strategy=view_consistent", "trainer.max_steps=60", "data.val_every=null",
                      "model.strategy.refine_start=20", "model.strategy.refine_every=20", "model.strategy.views=3",
                      f"+callbacks.keep._target_={__name__}.KeepModule")
    metrics = train(cfg)  # refinements at 20 and 40 drew and scored three views each
    assert metrics["step"] == 60
    model, views = KeepModule.kept["module"], KeepModule.kept["views"]
    high, drawn, seen = model.view_scores(torch.tensor([0, 1]), 0.5)
    # a Gaussian's blend weights summed over pixels, summed over the Gaussians, are the pixels' accumulation
    model.eval()
    accumulated = high_accumulated = 0.0
    with torch.no_grad():
        for index in (0, 1):
            out, _ = model.draw(views.K[index], views.c2w[index], views.height, views.width)
            error = (out["rgb"] - as_float_rgb(views.images[index])).abs().mean(dim=-1)
            accumulated += float(out["accumulation"].sum()) / 2
            high_accumulated += float(out["accumulation"][error > 0.5 * error.max()].sum()) / 2
    assert accumulated > 1.0 and high_accumulated > 0.1
    assert float(drawn.sum()) == pytest.approx(accumulated, rel=1e-4)
    assert float(high.sum()) == pytest.approx(high_accumulated, rel=1e-4)
    assert bool(seen.any()) and float(drawn[~seen].abs().sum()) == 0.0
