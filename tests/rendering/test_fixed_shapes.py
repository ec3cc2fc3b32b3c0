"""A training step of fixed shapes (issue 38's first part): an occupancy grid marched into a fixed sample capacity
and the renderer's one pass over a table of steps give what the variable-size path gives, and a training step of
the GPU presets on the CPU makes the host wait for the device nowhere (counted with HostSyncs)."""

import json

import pytest
import torch

from nerf_lightning.geometry.space import SceneSpace
from nerf_lightning.rendering import OccupancyGrid, OccupancyGridSampler, RoundsRenderer, TableRenderer
from nerf_lightning.rendering.march_fixed import march_rays_fixed
from nerf_lightning.rendering.occupancy import march_rays
from nerf_lightning.rendering.packed import RaySamples
from nerf_lightning.training.syncs import HOST_DATA
from tests.conftest import run_cli
from tests.rendering.test_occupancy import UNIT_BOX, BallField, random_grid, rays_towards_origin


def test_a_fixed_capacity_holds_the_same_steps_in_order_then_padding_of_zero_width():
    grid = random_grid(seed=0, fraction=0.3)
    rays_o, rays_d = rays_towards_origin(100, seed=1)
    space = SceneSpace(2.0, 6.0)
    rays = space.rays(rays_o, rays_d)
    variable = OccupancyGridSampler(grid, step_size=0.05).sample(rays, space, None, perturb=False)
    t_enter, t_exit = space.ray_range(rays, grid.aabb)
    reach = 2.0 * 3.0**0.5  # the unit box's diagonal
    fixed = march_rays_fixed(grid, rays_o, rays_d, t_enter, t_exit, 0.05, False, capacity=len(variable) + 50, reach=reach)
    real = fixed.t_ends > fixed.t_starts
    assert int(real.sum()) == len(variable) and bool(real[: len(variable)].all()) and not bool(real[len(variable):].any())
    for name in ("ray_indices", "t_starts", "t_ends"):
        torch.testing.assert_close(getattr(fixed, name)[: len(variable)], getattr(variable, name))
    assert bool((fixed.ray_indices[len(variable):] == 100).all()) and bool(fixed.extras["complete"].all())
    short = march_rays_fixed(grid, rays_o, rays_d, t_enter, t_exit, 0.05, False, capacity=len(variable) // 2, reach=reach)
    cut = int(short.ray_indices[-1])
    assert short.extras["complete"].tolist() == [ray < cut for ray in range(100)]


def test_the_density_pass_keeps_what_the_variable_march_keeps_in_a_fixed_capacity():
    grid = OccupancyGrid(UNIT_BOX, resolution=8)
    field = BallField()
    rays_o, rays_d = rays_towards_origin(64, seed=7, spread=0.2)
    space = SceneSpace(2.0, 6.0)
    rays = space.rays(rays_o, rays_d)
    t_enter, t_exit = space.ray_range(rays, grid.aabb)
    options = {"density_fn": field.density, "alpha_threshold": 1e-3, "early_stop_eps": 1e-4}
    variable = march_rays(grid, rays_o, rays_d, t_enter, t_exit, 0.02, False, **options)
    everything = march_rays(grid, rays_o, rays_d, t_enter, t_exit, 0.02, False)
    assert len(variable) < 0.6 * len(everything)  # the steps behind the ball are dropped
    fixed = march_rays_fixed(grid, rays_o, rays_d, t_enter, t_exit, 0.02, False, capacity=len(variable) + 10, reach=2.0 * 3.0**0.5,
                       march_capacity=len(everything) + 10, **options)
    for name in ("ray_indices", "t_starts", "t_ends"):
        torch.testing.assert_close(getattr(fixed, name)[: len(variable)], getattr(variable, name))
    assert not (fixed.t_ends > fixed.t_starts)[len(variable):].any() and bool(fixed.extras["complete"].all())


def test_rays_that_fit_counts_what_the_rays_held_whole_want():
    grid = random_grid(seed=0, fraction=0.3)
    rays_o, rays_d = rays_towards_origin(400, seed=2)
    space = SceneSpace(2.0, 6.0)
    t_enter, t_exit = space.ray_range(space.rays(rays_o, rays_d), grid.aabb)
    reach = 2.0 * 3.0**0.5
    wanted = len(march_rays(grid, rays_o, rays_d, t_enter, t_exit, 0.05, False))  # every occupied step of the 400 rays
    whole = march_rays_fixed(grid, rays_o, rays_d, t_enter, t_exit, 0.05, False, capacity=wanted + 10, reach=reach)
    assert float(whole.extras["rays_that_fit"]) == pytest.approx((wanted + 10) * 400 / wanted)
    # a quarter of what they want: the estimate from the rays held whole (the first ones), near the whole batch's
    short = march_rays_fixed(grid, rays_o, rays_d, t_enter, t_exit, 0.05, False, capacity=wanted // 4, reach=reach)
    assert float(short.extras["rays_that_fit"]) == pytest.approx((wanted // 4) * 400 / wanted, rel=0.3)
    # with the density pass: the fewer of the two buffers' counts
    field = BallField()
    pruned = march_rays_fixed(grid, rays_o, rays_d, t_enter, t_exit, 0.05, False, capacity=wanted // 8, reach=reach,
                        march_capacity=wanted + 10, density_fn=field.density, alpha_threshold=1e-3, early_stop_eps=1e-4)
    kept = len(march_rays(grid, rays_o, rays_d, t_enter, t_exit, 0.05, False, density_fn=field.density, alpha_threshold=1e-3,
                          early_stop_eps=1e-4))
    assert float(pruned.extras["rays_that_fit"]) == pytest.approx(min((wanted // 8) * 400 / kept, (wanted + 10) * 400 / wanted))


class NoTruth:
    """A field-space map (the identity) that refuses to be asked for its truth, as torch 2.11's dynamo cannot tell the
    truth of a bound method (the scene space's ``to_field``): ``to_field or identity`` failed the GPU presets'
    compiled step there ("Unsupported: Data-dependent branching"; later versions pass it, the CPU's among them)."""

    def __call__(self, points: torch.Tensor) -> torch.Tensor:
        return points

    def __bool__(self) -> bool:
        raise AssertionError("the march asked a to_field for its truth: compare it with None")


def test_the_march_never_asks_its_field_space_map_for_its_truth():
    grid = random_grid(seed=0, fraction=0.3)
    rays_o, rays_d = rays_towards_origin(32, seed=1)
    space = SceneSpace(2.0, 6.0)
    t_enter, t_exit = space.ray_range(space.rays(rays_o, rays_d), grid.aabb)
    options = {"density_fn": BallField().density, "alpha_threshold": 1e-3, "early_stop_eps": 1e-4}
    for march, extra in ((march_rays, {}), (march_rays_fixed, {"capacity": 4096, "reach": 2.0 * 3.0**0.5}),
                         (march_rays_fixed, {"capacity": 4096, "reach": 2.0 * 3.0**0.5, "march_capacity": 8192})):
        with_map = march(grid, rays_o, rays_d, t_enter, t_exit, 0.05, False, to_field=NoTruth(), **options, **extra)
        without = march(grid, rays_o, rays_d, t_enter, t_exit, 0.05, False, **options, **extra)
        torch.testing.assert_close(with_map.t_starts, without.t_starts)


@pytest.mark.parametrize("sampler", ["occupancy", "dense"])
def test_one_pass_over_the_table_equals_the_rounds_in_values_and_gradients(sampler):
    grid = OccupancyGrid(UNIT_BOX, resolution=8)
    field = BallField()
    rays_o, rays_d = rays_towards_origin(64, seed=7, spread=0.2)
    space = SceneSpace(2.0, 6.0, background=(1.0, 0.5, 0.0))
    rays = space.rays(rays_o, rays_d)
    if sampler == "occupancy":  # the rounds render the variable march, the table its fixed-capacity twin (padded)
        t_enter, t_exit = space.ray_range(rays, grid.aabb)
        table_samples = march_rays_fixed(grid, rays_o, rays_d, t_enter, t_exit, 0.02, False, capacity=20_000, reach=2.0 * 3.0**0.5)
        round_samples = OccupancyGridSampler(grid, step_size=0.02).sample(rays, space, field, perturb=False)
    else:
        t = torch.linspace(2.0, 6.0, 65)
        table_samples = round_samples = RaySamples.from_edges(t.expand(64, 65).contiguous())
    results = []
    for renderer, samples in ((RoundsRenderer(early_stop_eps=0.0, samples_per_round=7), round_samples),
                              (TableRenderer(), table_samples)):
        field.scale.grad = None
        out = renderer(field, rays, samples, space)
        (out["rgb"].sum() + out["depth"].sum()).backward()
        results.append((out, field.scale.grad.clone()))
    (rounds, rounds_grad), (table, table_grad) = results
    for key in ("rgb", "depth", "accumulation"):
        torch.testing.assert_close(table[key], rounds[key])
    real = len(round_samples)
    torch.testing.assert_close(table["weights"][:real], rounds["weights"])
    assert not table["weights"][real:].any()
    torch.testing.assert_close(table_grad, rounds_grad)
    padded = RoundsRenderer(early_stop_eps=0.0, samples_per_round=7)(field, rays, table_samples, space)  # the rounds skip padding
    torch.testing.assert_close(padded["rgb"], rounds["rgb"])
    samples = table_samples
    assert int(table["n_evaluated"]) == int((samples.t_ends > samples.t_starts).sum())


# a training step of the GPU presets, counted on the CPU with everything nerf-train runs around it (the default
# callbacks, the progress bar, the logger, drawing the next batch): one waits for nothing after the first steps (the
# grid's warm-up refreshes and Lightning's first step build what later steps reuse). Named exceptions: the steps that
# log (every trainer.log_every_n_steps: the logger, the progress bar and the PSNR history read the metrics back; set
# past the run here) and the NaN guard (FieldModule.on_before_backward), which reads the loss back every step on a
# CPU and on those steps on a GPU; it is switched off here to count the rest. The step runs plainly
# (model.compile=false): a dispatch mode sees every op of a plain step, and none inside a compiled graph (whose ops
# are those of the plain one).
PRESETS = {  # the presets as they are, on small scenes, their buffers sized for 256 rays
    "nerfacto_360_gpu": ["experiment=nerfacto_360_gpu", "data/scene=turntable", "data.scene.size=32", "data.scene.n_photos=16"],
    # the grid refreshed every other step, past its warm-up from the second: the refreshes on the device counted too
    "fast_blender_gpu": ["experiment=fast_blender_gpu", "data/scene=procedural", "data.scene.size=32", "model.sampler.grid.resolution=32",
                         "model.sampler.capacity=16384", "model.sampler.march_capacity=65536",
                         "model.sampler.grid.update_every=2", "model.sampler.grid.warmup_steps=2"],
}


@pytest.mark.parametrize("preset", list(PRESETS))
def test_a_fixed_shape_training_step_never_waits_for_the_device(preset, tmp_path, scene_cache, monkeypatch):
    monkeypatch.setenv("NERF_LIGHTNING_CACHE", str(scene_cache))
    counts = tmp_path / "syncs.json"
    run_cli("train", *PRESETS[preset], "trainer.max_steps=5", "data.val_every=null", "trainer.log_every_n_steps=100",
            "data.batch_size=256", "model.compile=false",
            f"+callbacks.syncs={{_target_: nerf_lightning.training.syncs.CountHostSyncs, path: {counts}, skip_nan_guard: true, host_data: true}}",
            f"paths.output_dir={tmp_path / 'run'}", cwd=tmp_path)
    steps = json.loads(counts.read_text())
    assert len(steps) == 5
    # no tensor made from host data either (host_data: true), which on a GPU is a copy that waits: the batch's rays
    # made one a step there (torch.as_tensor(1.0, device=...) in pixel_to_camera), which no other count shows
    assert steps[1:-1] == [{}, {}, {}], steps
    # the last step's count runs on to the final validation, whose data loader draws its seed as a host tensor's item
    # (on the host's generator: no wait for a GPU), after Lightning's checkpoint callbacks have made the epoch and
    # step numbers host tensors (on the host: no copy)
    assert {key: value for key, value in steps[-1].items() if key != HOST_DATA} in ({}, {"aten._local_scalar_dense": 1}), steps


def test_a_renderer_of_an_old_config_is_the_mode_its_flag_named():
    """Checkpoints and configs from before model/renderer=rounds|table name VolumeRenderer with fixed_shapes."""
    from hydra.utils import instantiate

    old = {"_target_": "nerf_lightning.rendering.VolumeRenderer", "early_stop_eps": 1e-3, "samples_per_round": 8,
           "gradient_scaling_distance": 1.0, "fixed_shapes": True}
    table = instantiate(old)
    assert isinstance(table, TableRenderer) and table.fixed_shapes and table.gradient_scaling_distance == 1.0
    assert (table.rounds.early_stop_eps, table.rounds.samples_per_round) == (1e-3, 8)
    rounds = instantiate({**old, "fixed_shapes": False})
    assert isinstance(rounds, RoundsRenderer) and not rounds.fixed_shapes and rounds.samples_per_round == 8


def test_the_old_renderer_keys_are_answered_with_the_new_group():
    from nerf_lightning.config import renamed_key_message

    assert "use model/renderer=table for a step of fixed shapes" in renamed_key_message(["model.renderer.fixed_shapes=true"])
    assert "use model/renderer=rounds" in renamed_key_message(["model/renderer=volume"])
    assert renamed_key_message(["model/renderer=table", "model.renderer.samples_per_round=8"]) is None
