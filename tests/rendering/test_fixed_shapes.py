"""A training step of fixed shapes (issue 38's first part): an occupancy grid marched into a fixed sample capacity
and the renderer's one pass over a table of steps give what the variable-size path gives, and a training step of
the GPU presets on the CPU makes the host wait for the device nowhere (counted with HostSyncs)."""

import json

import pytest
import torch

from nerf_lightning.geometry.space import SceneSpace
from nerf_lightning.rendering import FixedShapeGridSampler, FixedShapeSamples, OccupancyGrid, OccupancyGridSampler, RoundsRenderer, TableRenderer
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
    assert bool((fixed.ray_indices[len(variable):] == 100).all()) and bool(fixed.complete.all())
    short = march_rays_fixed(grid, rays_o, rays_d, t_enter, t_exit, 0.05, False, capacity=len(variable) // 2, reach=reach)
    cut = int(short.ray_indices[-1])
    assert short.complete.tolist() == [ray < cut for ray in range(100)]


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
    assert not (fixed.t_ends > fixed.t_starts)[len(variable):].any() and bool(fixed.complete.all())


def test_rays_that_fit_counts_what_the_rays_held_whole_want():
    grid = random_grid(seed=0, fraction=0.3)
    rays_o, rays_d = rays_towards_origin(400, seed=2)
    space = SceneSpace(2.0, 6.0)
    t_enter, t_exit = space.ray_range(space.rays(rays_o, rays_d), grid.aabb)
    reach = 2.0 * 3.0**0.5
    wanted = len(march_rays(grid, rays_o, rays_d, t_enter, t_exit, 0.05, False))  # every occupied step of the 400 rays
    whole = march_rays_fixed(grid, rays_o, rays_d, t_enter, t_exit, 0.05, False, capacity=wanted + 10, reach=reach)
    assert float(whole.rays_that_fit) == pytest.approx((wanted + 10) * 400 / wanted)
    # a quarter of what they want: the estimate from the rays held whole (the first ones), near the whole batch's
    short = march_rays_fixed(grid, rays_o, rays_d, t_enter, t_exit, 0.05, False, capacity=wanted // 4, reach=reach)
    assert float(short.rays_that_fit) == pytest.approx((wanted // 4) * 400 / wanted, rel=0.3)
    # with the density pass: the fewer of the two buffers' counts
    field = BallField()
    pruned = march_rays_fixed(grid, rays_o, rays_d, t_enter, t_exit, 0.05, False, capacity=wanted // 8, reach=reach,
                        march_capacity=wanted + 10, density_fn=field.density, alpha_threshold=1e-3, early_stop_eps=1e-4)
    kept = len(march_rays(grid, rays_o, rays_d, t_enter, t_exit, 0.05, False, density_fn=field.density, alpha_threshold=1e-3,
                          early_stop_eps=1e-4))
    assert float(pruned.rays_that_fit) == pytest.approx(min((wanted // 8) * 400 / kept, (wanted + 10) * 400 / wanted))


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
    if sampler == "occupancy":  # the rounds render the variable march, either renderer its fixed-capacity twin (padded)
        t_enter, t_exit = space.ray_range(rays, grid.aabb)
        table_samples = march_rays_fixed(grid, rays_o, rays_d, t_enter, t_exit, 0.02, False, capacity=20_000, reach=2.0 * 3.0**0.5)
        round_samples = OccupancyGridSampler(grid, step_size=0.02).sample(rays, space, field, perturb=False)
        assert isinstance(table_samples, FixedShapeSamples)
        one_pass = (TableRenderer(), RoundsRenderer())  # the samples' shape tells the rounds renderer too
    else:
        t = torch.linspace(2.0, 6.0, 65)
        table_samples = round_samples = RaySamples.from_edges(t.expand(64, 65).contiguous())
        one_pass = (TableRenderer(),)
    results = []
    for renderer, samples in ((RoundsRenderer(early_stop_eps=0.0, samples_per_round=7), round_samples),
                              *((renderer, table_samples) for renderer in one_pass)):
        field.scale.grad = None
        out = renderer(field, rays, samples, space)
        (out["rgb"].sum() + out["depth"].sum()).backward()
        results.append((out, field.scale.grad.clone()))
    (rounds, rounds_grad), *tables = results
    real = len(round_samples)
    for table, table_grad in tables:
        for key in ("rgb", "depth", "accumulation"):
            torch.testing.assert_close(table[key], rounds[key])
        torch.testing.assert_close(table["weights"][:real], rounds["weights"])
        assert not table["weights"][real:].any()
        torch.testing.assert_close(table_grad, rounds_grad)
    table = tables[0][0]
    # the same samples without their table's shape go in rounds, which skip the padding
    packed = RaySamples(table_samples.ray_indices, table_samples.t_starts, table_samples.t_ends, table_samples.n_rays)
    padded = RoundsRenderer(early_stop_eps=0.0, samples_per_round=7)(field, rays, packed, space)
    torch.testing.assert_close(padded["rgb"], rounds["rgb"])
    samples = table_samples
    assert int(table["n_evaluated"]) == int((samples.t_ends > samples.t_starts).sum())


def test_the_fixed_shape_sampler_trains_on_what_the_occupancy_grid_sampler_marches_and_evaluates_as_it():
    grid = OccupancyGrid(UNIT_BOX, resolution=8)
    grid.mark_from_density(BallField().density, step_size=0.02)
    field = BallField()
    rays_o, rays_d = rays_towards_origin(64, seed=7, spread=0.2)
    space = SceneSpace(2.0, 6.0)
    rays = space.rays(rays_o, rays_d)
    fixed, variable = FixedShapeGridSampler(grid, step_size=0.02, samples_per_step=20_000), OccupancyGridSampler(grid, step_size=0.02)
    torch.manual_seed(3)  # the same random shift of each ray's steps
    train_fixed = fixed.sample(rays, space, field, perturb=True)
    torch.manual_seed(3)
    train_variable = variable.sample(rays, space, field, perturb=True)
    assert isinstance(train_fixed, FixedShapeSamples) and len(train_fixed) == 20_000 and bool(train_fixed.complete.all())
    for name in ("ray_indices", "t_starts", "t_ends"):
        torch.testing.assert_close(getattr(train_fixed, name)[: len(train_variable)], getattr(train_variable, name))
    renderer = RoundsRenderer(early_stop_eps=0.0)
    torch.testing.assert_close(renderer(field, rays, train_fixed, space)["rgb"], renderer(field, rays, train_variable, space)["rgb"])
    with torch.no_grad():  # evaluation: every occupied step, as the occupancy-grid sampler marches them
        evaluated = fixed.sample(rays, space, field, perturb=False)
        assert type(evaluated) is RaySamples
        torch.testing.assert_close(evaluated.t_starts, variable.sample(rays, space, field, perturb=False).t_starts)
    calls = []
    grid.cells_on_device = lambda step: (calls.append(step), OccupancyGrid.cells_on_device(grid, step))[1]
    fixed.update(0, field)  # its refreshes draw their cells on the device
    variable.update(16, field)
    assert calls == [0]


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
                         "model.sampler.samples_per_step=16384", "model.sampler.density_pass_samples=65536",
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


def test_the_old_renderer_and_capacity_keys_are_answered_with_the_new_ones():
    from nerf_lightning.config import renamed_key_message

    assert "use model/sampler=fixed_shape_grid (an occupancy grid) or model/renderer=table" in renamed_key_message(
        ["model.renderer.fixed_shapes=true"])
    assert "use model/renderer=rounds" in renamed_key_message(["model/renderer=volume"])
    assert renamed_key_message(["model/renderer=table", "model.renderer.samples_per_round=8"]) is None
    assert renamed_key_message(["model.sampler.capacity=16384"]).endswith(
        "use model.sampler.samples_per_step (with model/sampler=fixed_shape_grid)")
    assert "use model.sampler.density_pass_samples" in renamed_key_message(["model.sampler.march_capacity=65536"])


def test_an_occupancy_grid_sampler_of_an_old_config_with_a_capacity_is_answered_in_one_line():
    grid = OccupancyGrid(UNIT_BOX, resolution=8)
    # the keys every config of before 0.4 had, null: as they were
    OccupancyGridSampler(grid, step_size=0.02, capacity=None, march_capacity=None, early_stop_eps=1e-4)
    with pytest.raises(ValueError, match="use model/sampler=fixed_shape_grid with model.sampler.samples_per_step=16384"):
        OccupancyGridSampler(grid, step_size=0.02, capacity=16384, march_capacity=None)


def test_the_fixed_shape_preset_composes_to_the_fixed_shape_sampler_and_compiles():
    from hydra.utils import instantiate

    from nerf_lightning.config import compose_config
    from nerf_lightning.rendering.renderer import check_compilable

    model = compose_config(["experiment=fast_blender_gpu", "paths.output_dir=unused"]).model
    assert (model.sampler.samples_per_step, model.sampler.density_pass_samples) == (262144, 1048576)
    sampler, renderer = instantiate(model.sampler), instantiate(model.renderer)
    assert isinstance(sampler, FixedShapeGridSampler) and type(renderer) is RoundsRenderer
    check_compilable(renderer, sampler)  # the samples tell the renderer: a step of fixed shapes
    check_compilable(TableRenderer(), sampler)
    with pytest.raises(ValueError, match="model.compile=true needs a training step of fixed shapes"):
        check_compilable(renderer, OccupancyGridSampler(sampler.grid))
