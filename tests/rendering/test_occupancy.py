"""Empty-space skipping: the occupancy grid, the ray marcher and packed compositing."""

import math

import pytest
import torch

from nerf_lightning.data.formats.procedural import surface_distance, trace
from nerf_lightning.geometry.contraction import Contraction
from nerf_lightning.geometry.rays import ray_aabb_intersect
from nerf_lightning.geometry.space import SceneSpace
from nerf_lightning.rendering import (
    OccupancyGrid,
    OccupancyGridSampler,
    RoundsRenderer,
    composite,
    composite_packed,
    exclusive_sum_packed,
    march_rays,
)
from nerf_lightning.rendering.occupancy import step_edges
from nerf_lightning.training.syncs import HostSyncs

UNIT_BOX = [-1.0, -1.0, -1.0, 1.0, 1.0, 1.0]
CUBE = list(Contraction.bounds)


def march(grid, rays_o, rays_d, near, far, step_size, perturb, space=None, **options):
    """march_rays over the range of a scene space from near to far (cut to the grid's box unless contracted)."""
    space = space or SceneSpace(near, far)
    t_enter, t_exit = space.ray_range(space.rays(rays_o, rays_d), grid.aabb)
    return march_rays(grid, rays_o, rays_d, t_enter, t_exit, step_size, perturb, to_field=space.to_field, **options)


def rays_towards_origin(count: int, seed: int, radius: float = 4.0, spread: float = 0.8) -> tuple[torch.Tensor, torch.Tensor]:
    generator = torch.Generator().manual_seed(seed)
    origins = torch.nn.functional.normalize(torch.randn(count, 3, generator=generator), dim=-1) * radius
    targets = (torch.rand(count, 3, generator=generator) * 2 - 1) * spread
    return origins, torch.nn.functional.normalize(targets - origins, dim=-1)


def test_ray_box_intersection():
    aabb = torch.tensor(UNIT_BOX)
    rays_o = torch.tensor([[-3.0, 0.0, 0.0], [0.0, 0.0, 0.0], [-3.0, 2.0, 0.0]])
    rays_d = torch.tensor([[1.0, 0.0, 0.0], [0.0, 0.0, 1.0], [1.0, 0.0, 0.0]])
    enter, exit_ = ray_aabb_intersect(rays_o, rays_d, aabb)
    torch.testing.assert_close(enter[:2], torch.tensor([2.0, -1.0]))
    torch.testing.assert_close(exit_[:2], torch.tensor([4.0, 1.0]))
    assert exit_[2] < enter[2]  # misses


def test_exclusive_sum_packed_restarts_at_every_ray():
    values = torch.tensor([1.0, 2.0, 3.0, 10.0, 20.0, 5.0])
    ray_indices = torch.tensor([0, 0, 0, 2, 2, 3])
    got = exclusive_sum_packed(values, ray_indices, n_rays=4)
    torch.testing.assert_close(got, torch.tensor([0.0, 1.0, 3.0, 0.0, 10.0, 0.0]))


def test_exclusive_sum_packed_of_rays_longer_than_a_row_equals_each_rays_own_cumsum():
    """Rays of 0 to 1500 samples: one row, several rows, rows of rows (ROW_LENGTH^2 < 1500); values and gradients."""
    from nerf_lightning.rendering.compositing import ROW_LENGTH, weights_from_alpha_packed

    assert ROW_LENGTH**2 < 1500
    generator = torch.Generator().manual_seed(0)
    counts = [1500, 0, 1, ROW_LENGTH, ROW_LENGTH + 1, 70, 3]
    ray_indices = torch.repeat_interleave(torch.arange(len(counts)), torch.tensor(counts))
    values = torch.rand(len(ray_indices), generator=generator, dtype=torch.float64, requires_grad=True)
    got = exclusive_sum_packed(values, ray_indices, n_rays=len(counts))
    expected = torch.cat([torch.cumsum(part, 0) - part for part in values.split(counts)])
    torch.testing.assert_close(got, expected)
    weights = torch.rand(len(got), generator=generator, dtype=torch.float64)
    (grad,) = torch.autograd.grad((got * weights).sum(), values)
    (expected_grad,) = torch.autograd.grad((expected * weights).sum(), values)
    torch.testing.assert_close(grad, expected_grad)
    # and the totals: what leaves each ray
    alpha = 0.01 * torch.rand(len(ray_indices), generator=generator, dtype=torch.float64)
    after = weights_from_alpha_packed(alpha, ray_indices, len(counts)).transmittance_after
    torch.testing.assert_close(after, torch.stack([torch.prod(1 - part) for part in alpha.split(counts)]))


def test_packed_compositing_equals_dense_compositing_of_the_same_samples():
    generator = torch.Generator().manual_seed(0)
    n_rays, n_samples = 6, 9
    t = torch.sort(2 + 4 * torch.rand(n_rays, n_samples + 1, generator=generator, dtype=torch.float64), dim=-1).values
    t_starts, t_ends = t[:, :-1], t[:, 1:]
    density = 3 * torch.rand(n_rays, n_samples, generator=generator, dtype=torch.float64)
    rgb = torch.rand(n_rays, n_samples, 3, generator=generator, dtype=torch.float64)
    background = torch.tensor([0.2, 0.5, 1.0], dtype=torch.float64)
    # every ray keeps a different number of its samples (ray 4 none): packed against each ray composited alone
    counts = [9, 1, 5, 7, 0, 3]
    keep = torch.arange(n_samples)[None, :] < torch.tensor(counts)[:, None]
    ray_indices = torch.arange(n_rays)[:, None].expand(-1, n_samples)[keep]
    packed = composite_packed(rgb[keep], density[keep], t_starts[keep], t_ends[keep], ray_indices, n_rays, background)
    for ray, count in enumerate(counts):
        if count == 0:
            torch.testing.assert_close(packed["rgb"][ray], background)
            assert packed["accumulation"][ray] == 0
            continue
        s = slice(0, count)
        dense = composite(rgb[ray : ray + 1, s], density[ray : ray + 1, s], (0.5 * (t_starts + t_ends))[ray : ray + 1, s],
                          (t_ends - t_starts)[ray : ray + 1, s], background)
        for key in ("rgb", "depth", "accumulation"):
            torch.testing.assert_close(packed[key][ray], dense[key][0])
        torch.testing.assert_close(packed["weights"][ray_indices == ray], dense["weights"][0])


def test_packed_compositing_is_differentiable():
    generator = torch.Generator().manual_seed(1)
    density = torch.rand(7, generator=generator, dtype=torch.float64, requires_grad=True)
    rgb = torch.rand(7, 3, generator=generator, dtype=torch.float64, requires_grad=True)
    t = torch.linspace(2, 3, 8, dtype=torch.float64)
    ray_indices = torch.tensor([0, 0, 0, 1, 1, 1, 1])

    def render(density, rgb):
        return composite_packed(rgb, density, t[:-1], t[1:], ray_indices, 2, torch.ones(3, dtype=torch.float64))["rgb"]

    assert torch.autograd.gradcheck(render, (density, rgb))


def random_grid(seed: int, fraction: float, resolution: int = 16) -> OccupancyGrid:
    grid = OccupancyGrid(UNIT_BOX, resolution=resolution)
    grid.binary.copy_(torch.rand(grid.binary.shape, generator=torch.Generator().manual_seed(seed)) < fraction)
    return grid


def test_marched_samples_lie_in_occupied_cells_between_near_and_far_in_order():
    grid = random_grid(seed=0, fraction=0.3)
    rays_o, rays_d = rays_towards_origin(200, seed=1)
    near, far = 3.2, 4.6  # cuts into the box from both sides for many rays
    generator = torch.Generator().manual_seed(2)
    samples = march(grid, rays_o, rays_d, near, far, step_size=0.05, perturb=True, generator=generator)
    ray_indices, t_starts, t_ends = samples.ray_indices, samples.t_starts, samples.t_ends
    assert len(ray_indices) > 100
    midpoints = rays_o[ray_indices] + rays_d[ray_indices] * (0.5 * (t_starts + t_ends))[:, None]
    assert grid.occupied(midpoints).all()
    assert (t_starts >= near).all() and (t_ends <= far + 1e-6).all() and (t_ends > t_starts).all()
    assert (ray_indices[1:] >= ray_indices[:-1]).all()
    same_ray = ray_indices[1:] == ray_indices[:-1]
    assert (t_starts[1:][same_ray] >= t_ends[:-1][same_ray] - 1e-6).all()


def test_marching_an_all_occupied_grid_covers_each_ray_inside_the_box_exactly():
    grid = OccupancyGrid(UNIT_BOX, resolution=8)  # starts all occupied
    rays_o, rays_d = rays_towards_origin(50, seed=3)
    samples = march(grid, rays_o, rays_d, 0.0, 10.0, step_size=0.03, perturb=False)
    ray_indices, t_starts, t_ends = samples.ray_indices, samples.t_starts, samples.t_ends
    enter, exit_ = ray_aabb_intersect(rays_o, rays_d, grid.aabb)
    covered = torch.zeros(50).index_add_(0, ray_indices, t_ends - t_starts)
    torch.testing.assert_close(covered, exit_ - enter, atol=1e-4, rtol=0)
    counts = torch.bincount(ray_indices, minlength=50)
    assert (counts == torch.ceil((exit_ - enter) / 0.03 - 1e-4)).all()


def test_cone_steps_grow_with_the_distance():
    edges = step_edges(0.05, 100.0, 0.01, 1 / 64)
    widths, starts = edges[1:] - edges[:-1], edges[:-1]
    assert edges.dtype == torch.float32 and float(edges[0]) == pytest.approx(0.05) and float(edges[-2]) < 100.0 <= float(edges[-1])
    # each step is max(step, cone * t) long: constant up to t = 0.64, then 1/64 of the distance
    torch.testing.assert_close(widths, torch.maximum(torch.full_like(starts, 0.01), starts / 64), atol=0.01, rtol=0.02)
    assert float(widths[0]) == pytest.approx(0.01, rel=1e-5) and float(widths[-1]) == pytest.approx(float(starts[-1]) / 64, rel=1e-5)  # float32
    assert len(edges) < 400  # 60 constant steps, then log(100 / 0.64) / log(1 + 1/64) geometric ones; 10 000 at a fixed step


def test_a_contracted_grid_marches_every_ray_from_near_to_far_with_cone_steps():
    grid = OccupancyGrid(CUBE, resolution=8)  # all occupied: all of space
    rays_o, rays_d = rays_towards_origin(40, seed=5, radius=0.5)  # inside the box
    near, far = 0.05, 50.0
    space = SceneSpace(near, far, contraction=Contraction())
    samples = march(grid, rays_o, rays_d, near, far, step_size=0.02, perturb=False, space=space, cone_angle=1 / 32)
    ray_indices, t_starts, t_ends = samples.ray_indices, samples.t_starts, samples.t_ends
    covered = torch.zeros(40).index_add_(0, ray_indices, t_ends - t_starts)
    torch.testing.assert_close(covered, torch.full((40,), far - near), rtol=1e-5, atol=1e-4)
    assert (torch.bincount(ray_indices, minlength=40) == len(step_edges(near, far, 0.02, 1 / 32)) - 1).all()
    # the cells far away are contracted ones: a grid whose outer shell is empty drops the far samples only
    grid.binary[1:-1, 1:-1, 1:-1] = True
    grid.binary[0], grid.binary[-1], grid.binary[:, 0], grid.binary[:, -1], grid.binary[:, :, 0], grid.binary[:, :, -1] = (False,) * 6
    kept = march(grid, rays_o, rays_d, near, far, step_size=0.02, perturb=False, space=space, cone_angle=1 / 32)
    midpoints = rays_o[kept.ray_indices] + rays_d[kept.ray_indices] * (0.5 * (kept.t_starts + kept.t_ends))[:, None]
    norms = midpoints.abs().amax(-1)
    # the outer shell of an 8-cell grid holds contracted |y| > 1.5, that is |x| > 1 / (2 - 1.5) = 2
    assert 0 < len(kept.ray_indices) < len(ray_indices) and float(norms.max()) <= 2.0 + 1e-4
    assert float(norms.max()) > 1.5  # and the cells inside it reach beyond the box (|x| <= 1)


def test_a_contracted_grid_refreshes_cells_all_over_space():
    grid = OccupancyGrid(CUBE, resolution=8, warmup_steps=10)
    contraction = Contraction()
    centres = grid.cell_centres().reshape(-1, 3)  # field space: contracted points
    # the outermost centres: contracted |y| = 2 - 0.25, so |x| = 1 / (2 - 1.75) = 4, four times the box's half-size
    torch.testing.assert_close(contraction.inverse(centres).abs().amax(-1).max(), torch.tensor(4.0))
    cells, inside = grid.cell_of(centres)
    assert bool(inside.all())
    assert torch.equal(cells, torch.stack(torch.meshgrid(*[torch.arange(8)] * 3, indexing="ij"), -1).reshape(-1, 3))
    # a field of the contracted scene that is dense only far away (|x| > 3, contracted |y| > 5/3)
    grid.update(0, lambda points: (contraction.inverse(points).abs().amax(-1) > 3.0).float() * 100.0, step_size=0.02)
    assert bool(grid.occupied(contraction(torch.tensor([[10.0, 0.0, 0.0]])))[0]) and not bool(grid.occupied(torch.zeros(1, 3))[0])


def test_an_empty_grid_gives_no_samples_and_the_background():
    grid = OccupancyGrid(UNIT_BOX, resolution=8)
    grid.binary.zero_()
    rays_o, rays_d = rays_towards_origin(10, seed=4)
    samples = march(grid, rays_o, rays_d, 2.0, 6.0, 0.05, perturb=True)
    assert len(samples) == 0 and samples.n_rays == 10


def test_early_stopping_drops_only_samples_behind_an_opaque_surface():
    grid = OccupancyGrid(UNIT_BOX, resolution=8)
    rays_o, rays_d = rays_towards_origin(64, seed=5, spread=0.3)

    def density(points):  # an opaque ball of radius 0.5
        return 50.0 * (points.norm(dim=-1) < 0.5).to(points.dtype)

    everything = march(grid, rays_o, rays_d, 2.0, 6.0, 0.02, perturb=False)
    culled = march(grid, rays_o, rays_d, 2.0, 6.0, 0.02, perturb=False, density_fn=density, early_stop_eps=1e-4)
    assert len(culled.ray_indices) < 0.8 * len(everything.ray_indices)

    def render(samples):
        ray_indices, t_starts, t_ends = samples.ray_indices, samples.t_starts, samples.t_ends
        points = rays_o[ray_indices] + rays_d[ray_indices] * (0.5 * (t_starts + t_ends))[:, None]
        rgb = torch.sigmoid(points)  # any colour field
        return composite_packed(rgb, density(points), t_starts, t_ends, ray_indices, 64, torch.ones(3))["rgb"]

    torch.testing.assert_close(render(culled), render(everything), atol=2e-4, rtol=0)


def test_a_grid_built_from_the_procedural_scenes_true_density_marks_its_surfaces_occupied():
    grid = OccupancyGrid([-1.3, -1.3, -1.3, 1.3, 1.3, 1.3], resolution=48)
    half_diagonal = math.sqrt(3) / 2 * 2.6 / 48

    # a cell holds a surface point only if its centre is within half a cell diagonal of the surface
    def density(points):
        return 1e3 * (surface_distance(points) < half_diagonal).to(points.dtype)

    grid.mark_from_density(density, step_size=0.01)
    rays_o, rays_d = rays_towards_origin(4000, seed=6, spread=1.0)
    t_hit = trace(rays_o, rays_d)["t"].float()
    hit = torch.isfinite(t_hit)
    assert hit.sum() > 2000
    surface_points = rays_o[hit] + rays_d[hit] * t_hit[hit, None]
    assert grid.occupied(surface_points).all()
    # and what is far from every surface is empty: most of the box
    centres = grid.cell_centres().reshape(-1, 3)
    far_from_surfaces = surface_distance(centres) > 2 * half_diagonal
    assert not grid.binary.reshape(-1)[far_from_surfaces].any()
    assert grid.binary.float().mean() < 0.3


@pytest.mark.parametrize("on_device", [False, True])
def test_grid_refresh_schedule_warmup_then_ema(on_device):
    grid = OccupancyGrid(UNIT_BOX, resolution=8, update_every=4, warmup_steps=8, decay=0.5, threshold=0.01, seed=3)
    update = grid.update
    grid.update = lambda *args, **kwargs: update(*args, **kwargs, draw=grid.cells_on_device if on_device else None)
    calls = []

    def constant(value):
        def density(points):
            calls.append(len(points))
            return torch.full(points.shape[:1], value)
        return density

    assert not grid.update(3, constant(1.0), step_size=0.1)
    assert grid.update(4, constant(1.0), step_size=0.1)
    assert calls == [512]  # warmup: every cell
    torch.testing.assert_close(grid.occupancy, torch.full((8, 8, 8), 0.1))
    assert grid.binary.all()
    grid.update(8, constant(0.0), step_size=0.1)  # after warmup: 128 random cells and 128 random occupied ones
    assert calls[-1] == 256
    halved = torch.isclose(grid.occupancy, torch.tensor(0.05))
    assert (halved | torch.isclose(grid.occupancy, torch.tensor(0.1))).all() and 0 < halved.sum() <= 256  # refreshed cells halve (EMA), the others keep their estimate
    again = OccupancyGrid(UNIT_BOX, resolution=8, update_every=4, warmup_steps=8, decay=0.5, seed=3)
    draw = again.cells_on_device if on_device else again.cells_on_host
    again.update(4, constant(1.0), step_size=0.1, draw=draw)
    again.update(8, constant(0.0), step_size=0.1, draw=draw)
    assert torch.equal(again.occupancy, grid.occupancy)  # refreshes are seeded by step: a resumed run refreshes alike


def test_a_refresh_on_the_device_picks_occupied_cells_and_reads_nothing_back():
    grid = OccupancyGrid(UNIT_BOX, resolution=8, update_every=1, warmup_steps=1, seed=5)
    grid.binary.zero_()
    grid.binary[2:4, 5, 1:7] = True  # 12 occupied cells
    occupied = set(grid.binary.flatten().nonzero()[:, 0].tolist())
    cells, unit = grid.cells_on_device(step=3)
    assert cells.shape == (256,) and unit.shape == (256, 3)
    picked = set(cells[128:].tolist())
    assert picked <= occupied and len(picked) == 12  # 128 picks among 12 cells: each of them, and only them
    assert (unit >= 0).all() and (unit <= 1).all()
    offset = unit * 8 - grid._coordinates(cells)  # each point inside its own cell
    assert (offset >= -1e-5).all() and (offset <= 1 + 1e-5).all()
    grid.binary.zero_()  # an empty grid: the picks fall back to uniform cells
    cells, _ = grid.cells_on_device(step=4)
    assert torch.equal(cells[128:], cells[:128])
    with HostSyncs() as syncs:
        grid.update(5, lambda points: torch.ones(len(points)), step_size=0.1, draw=grid.cells_on_device)
    assert syncs.total == 0, syncs.counts
    with HostSyncs() as syncs:  # the host's draws list the occupied cells: a size that depends on the grid
        grid.update(6, lambda points: torch.ones(len(points)), step_size=0.1)
    assert syncs.counts["aten.nonzero"] >= 1


class BallField(torch.nn.Module):
    """An opaque ball of radius 0.5 whose colour varies in space, with a learnable density scale."""

    def __init__(self):
        super().__init__()
        self.scale = torch.nn.Parameter(torch.tensor(50.0))

    def density(self, points):
        return self.scale * (points.norm(dim=-1) < 0.5).to(points.dtype)

    def forward(self, points, directions):
        return {"rgb": torch.sigmoid(points + directions), "density": self.density(points)}


def test_rendering_in_rounds_equals_compositing_every_marched_sample():
    grid = OccupancyGrid(UNIT_BOX, resolution=8)
    field = BallField()
    rays_o, rays_d = rays_towards_origin(64, seed=7, spread=0.2)  # most hit the ball
    space = SceneSpace(2.0, 6.0, background=(1.0, 0.5, 0.0))
    rays = space.rays(rays_o, rays_d)
    samples = OccupancyGridSampler(grid, step_size=0.02).sample(rays, space, field, perturb=False)
    points = rays.points(samples.ray_indices, 0.5 * (samples.t_starts + samples.t_ends))
    out = field(points, rays_d[samples.ray_indices])
    everything = composite_packed(out["rgb"], out["density"], samples.t_starts, samples.t_ends, samples.ray_indices, 64, space.background)
    exact = RoundsRenderer(early_stop_eps=0.0, samples_per_round=7)(field, rays, samples, space)
    assert exact["n_evaluated"] == len(samples)
    for key in ("rgb", "depth", "accumulation", "weights"):
        torch.testing.assert_close(exact[key], everything[key])
    stopped = RoundsRenderer(early_stop_eps=1e-4, samples_per_round=7)(field, rays, samples, space)
    assert stopped["n_evaluated"] < 0.6 * len(samples)  # the samples behind the ball are never evaluated
    torch.testing.assert_close(stopped["rgb"], everything["rgb"], atol=2e-4, rtol=0)
    stopped["rgb"].sum().backward()
    assert field.scale.grad is not None and field.scale.grad != 0


def test_the_renderer_gives_each_ray_of_a_long_batch_its_own_float32_transmittance():
    """Many rays of many samples: the round tables restart at every ray, so float32 matches a float64 reference."""
    generator = torch.Generator().manual_seed(11)
    n_rays, per_ray = 512, 300
    edges = torch.sort(2 + 4 * torch.rand(n_rays, per_ray + 1, generator=generator, dtype=torch.float64), dim=-1).values
    density = 2 * torch.rand(n_rays, per_ray, generator=generator, dtype=torch.float64)
    rgb = torch.rand(n_rays, per_ray, 3, generator=generator, dtype=torch.float64)
    reference = composite(rgb, density, 0.5 * (edges[:, 1:] + edges[:, :-1]), edges[:, 1:] - edges[:, :-1], torch.ones(3, dtype=torch.float64))
    ray_indices = torch.arange(n_rays).repeat_interleave(per_ray)
    packed = composite_packed(rgb.reshape(-1, 3).float(), density.reshape(-1).float(), edges[:, :-1].reshape(-1).float(),
                              edges[:, 1:].reshape(-1).float(), ray_indices, n_rays, torch.ones(3))
    assert (packed["rgb"].double() - reference["rgb"]).abs().max() < 1e-5
    assert (packed["weights"].double() - reference["weights"].reshape(-1)).abs().max() < 1e-5


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA device")
def test_marching_and_rendering_give_the_same_result_on_cuda():
    grid = random_grid(seed=8, fraction=0.5)
    field = BallField()
    rays_o, rays_d = rays_towards_origin(256, seed=9, spread=0.6)
    sampler, renderer = OccupancyGridSampler(grid, step_size=0.02), RoundsRenderer()

    def render(device):
        space = SceneSpace(2.0, 6.0).to(device)
        rays = space.rays(rays_o.to(device), rays_d.to(device))
        return renderer(field.to(device), rays, sampler.to(device).sample(rays, space, field, perturb=False), space)

    on_cpu, on_cuda = render("cpu"), render("cuda")
    assert on_cuda["n_evaluated"] == on_cpu["n_evaluated"]
    for key in ("rgb", "depth", "accumulation"):
        torch.testing.assert_close(on_cuda[key].cpu(), on_cpu[key], atol=1e-4, rtol=1e-4)


def test_a_refresh_under_bf16_autocast_measures_density_in_float32():
    """Under bf16-mixed an untrained field's densities round to a few values (1 + 1e-3 x is 1.0 in bfloat16); a grid
    refreshed from those has no cell above its mean: no samples, no gradient, training never starts. The refresh
    leaves autocast, so the grid keeps the cells whose float32 density is above the mean."""
    torch.manual_seed(0)
    layer = torch.nn.Linear(3, 1)
    with torch.no_grad():
        layer.weight.fill_(1e-3)
        layer.bias.fill_(1.0)
    grid = OccupancyGrid([-1.0, -1.0, -1.0, 1.0, 1.0, 1.0], resolution=16, update_every=1, warmup_steps=10)
    with torch.autocast("cpu", dtype=torch.bfloat16):
        assert layer(torch.rand(5, 3)).dtype == torch.bfloat16
        assert len(torch.unique(layer(torch.rand(4096, 3) * 2 - 1))) <= 2  # what the grid would have seen
        grid.update(0, lambda points: layer(points)[:, 0], step_size=0.01)
    assert 0.3 < grid.binary.float().mean() < 0.7
