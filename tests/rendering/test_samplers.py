"""Every sampler: packed samples between near and far, in order, for any field; the samplers' own state and losses."""

import pytest
import torch

import nerf_lightning.fields.grid as grid_module
from nerf_lightning.fields import DensityField, GridField, NeRFField
from nerf_lightning.fields.hash_grid import HashGridEncoding
from nerf_lightning.geometry.contraction import Contraction
from nerf_lightning.geometry.space import SceneSpace
from nerf_lightning.rendering import (
    HierarchicalSampler,
    OccupancyGrid,
    OccupancyGridSampler,
    ProposalSampler,
    StratifiedSampler,
    RoundsRenderer,
)
from nerf_lightning.rendering.packed import RaySamples
from nerf_lightning.rendering.samplers import stratified_edges
from nerf_lightning.rendering.samplers.proposal import distortion_loss, interlevel_loss

BOX = [-1.5, -1.5, -1.5, 1.5, 1.5, 1.5]


def small_nerf():
    return NeRFField(position_frequencies=4, direction_frequencies=2, hidden_width=16, hidden_layers=2, skip_layer=None, view_width=8)


def small_grid_field(aabb=BOX):
    return GridField(aabb=aabb, encoding=HashGridEncoding(n_levels=4, log2_table_size=12, max_resolution=64), hidden_width=16, geometry_features=7)


SAMPLERS = {
    "stratified": lambda: StratifiedSampler(n_samples=24),
    "hierarchical": lambda: HierarchicalSampler(small_nerf(), n_samples=16, n_fine_samples=16),
    "occupancy_grid": lambda: OccupancyGridSampler(OccupancyGrid(BOX, resolution=8), step_size=0.05),
    "proposal": lambda: ProposalSampler([small_density_field(), small_density_field()], proposal_samples=(32, 16), field_samples=12),
}


def small_density_field():
    return DensityField(BOX, HashGridEncoding(n_levels=3, log2_table_size=10, max_resolution=32))
FIELDS = {"nerf": small_nerf, "hash_grid": small_grid_field}


def camera_rays(space, count=64, seed=0):
    generator = torch.Generator().manual_seed(seed)
    origins = torch.nn.functional.normalize(torch.randn(count, 3, generator=generator), dim=-1) * 4.0
    targets = (torch.rand(count, 3, generator=generator) * 2 - 1) * 0.8
    return space.rays(origins, torch.nn.functional.normalize(targets - origins, dim=-1))


def assert_packed_in_range(samples, near, far):
    assert len(samples) > 0
    assert (samples.ray_indices[1:] >= samples.ray_indices[:-1]).all()
    assert (samples.t_starts >= near - 1e-5).all() and (samples.t_ends <= far + 1e-5).all()
    assert (samples.t_ends >= samples.t_starts).all()
    same_ray = samples.ray_indices[1:] == samples.ray_indices[:-1]
    assert (samples.t_starts[1:][same_ray] >= samples.t_ends[:-1][same_ray] - 1e-5).all()


@pytest.mark.parametrize("field_name", sorted(FIELDS))
@pytest.mark.parametrize("sampler_name", sorted(SAMPLERS))
@pytest.mark.parametrize("perturb", [False, True])
def test_any_sampler_with_any_field_renders_samples_in_order_between_near_and_far(sampler_name, field_name, perturb):
    torch.manual_seed(0)
    sampler, field, space = SAMPLERS[sampler_name](), FIELDS[field_name](), SceneSpace(2.0, 6.0)
    rays = camera_rays(space)
    samples = sampler.sample(rays, space, field, perturb=perturb)
    assert_packed_in_range(samples, 2.0, 6.0)
    out = RoundsRenderer(early_stop_eps=0.0)(field, rays, samples, space)
    assert out["rgb"].shape == (64, 3) and out["weights"].shape == (len(samples),) and out["n_evaluated"] == len(samples)
    target = torch.rand(64, 3)
    losses = sampler.losses(samples, out, target)
    loss = torch.nn.functional.mse_loss(out["rgb"], target) + sum(losses.values())
    loss.backward()
    assert all(p.grad is not None for p in field.parameters() if p.requires_grad)
    if sampler_name == "hierarchical":
        assert set(losses) == {"coarse_rgb"} and any(p.grad is not None for p in sampler.coarse_field.parameters())
    elif sampler_name == "proposal":
        assert set(losses) == ({"interlevel", "distortion"} if perturb else {"distortion"})
        assert all(p.grad is not None for p in sampler.proposal_fields.parameters()) == perturb  # they learn in training only
    else:
        assert losses == {}


def test_stratified_edges_cover_each_ray_from_enter_to_exit():
    torch.manual_seed(0)
    t_enter, t_exit = torch.tensor([2.0, 0.5]), torch.tensor([6.0, 1.0])
    even = stratified_edges(t_enter, t_exit, 4, perturb=False)
    torch.testing.assert_close(even, torch.tensor([[2.0, 3.0, 4.0, 5.0, 6.0], [0.5, 0.625, 0.75, 0.875, 1.0]]))
    jittered = stratified_edges(torch.full((1000,), 2.0), torch.full((1000,), 6.0), 4, perturb=True)
    assert (jittered[:, 1:] >= jittered[:, :-1]).all() and (jittered >= 2.0).all() and (jittered <= 6.0).all()
    # each inner edge moves between the midpoints of its neighbours: uniform on [k + 1.5, k + 2.5] about k + 2
    torch.testing.assert_close(jittered[:, 1:-1].mean(0), torch.tensor([3.0, 4.0, 5.0]), atol=0.05, rtol=0)


def test_hierarchical_samples_crowd_where_the_coarse_network_sees_a_surface():
    class Slab(torch.nn.Module):  # opaque between t = 4 and 4.5 along the rays through the origin
        def density(self, points):
            return 100.0 * (points[..., 0].abs() < 0.25).float()

        def forward(self, points, directions):
            return {"rgb": torch.ones_like(points) * 0.5, "density": self.density(points)}

    space = SceneSpace(2.0, 6.0)
    rays = space.rays(torch.tensor([[-4.0, 0.0, 0.0]]), torch.tensor([[1.0, 0.0, 0.0]]))
    samples = HierarchicalSampler(Slab(), n_samples=16, n_fine_samples=64).sample(rays, space, Slab(), perturb=False)
    mids = 0.5 * (samples.t_starts + samples.t_ends)
    near_surface = ((mids > 3.5) & (mids < 4.0)).sum()
    assert near_surface >= 40  # of 80 intervals, most in the one coarse bin where the ray meets the slab


def test_the_occupancy_grid_sampler_learns_from_the_field_and_skips_empty_space():
    grid = OccupancyGrid(BOX, resolution=16, update_every=1, warmup_steps=10)
    sampler = OccupancyGridSampler(grid, step_size=0.02)

    class Ball(torch.nn.Module):
        def density(self, points):
            return 100.0 * (points.norm(dim=-1) < 0.5).float()

        def forward(self, points, directions):
            return {"rgb": torch.sigmoid(points), "density": self.density(points)}

    space, field = SceneSpace(2.0, 6.0), Ball()
    rays = camera_rays(space, count=256, seed=1)
    before = len(sampler.sample(rays, space, field, perturb=False))
    sampler.update(0, field)
    after = sampler.sample(rays, space, field, perturb=False)
    assert len(after) < 0.25 * before
    points = rays.points(after.ray_indices, 0.5 * (after.t_starts + after.t_ends))
    assert points.norm(dim=-1).max() < 0.5 + 3 ** 0.5 * 3.0 / 16  # within a cell of the ball


def test_a_contracted_scene_marches_to_far_and_feeds_the_field_contracted_points():
    seen = []

    class Recorder(torch.nn.Module):
        def density(self, points):
            return torch.zeros(points.shape[:-1])

        def forward(self, points, directions):
            seen.append(points)
            return {"rgb": torch.zeros_like(points), "density": self.density(points)}

    space = SceneSpace(0.05, 100.0, contraction=Contraction())
    sampler = OccupancyGridSampler(OccupancyGrid(list(Contraction.bounds), resolution=8), step_size=0.01, cone_angle=1 / 64)
    rays = space.rays(torch.zeros(8, 3), torch.nn.functional.normalize(torch.randn(8, 3, generator=torch.Generator().manual_seed(0)), dim=-1))
    samples = sampler.sample(rays, space, Recorder(), perturb=False)
    assert float(samples.t_ends.max()) == pytest.approx(100.0)
    RoundsRenderer()(Recorder(), rays, samples, space)
    points = torch.cat(seen)
    assert points.abs().max() < 2.0 and points.abs().max() > 1.9


def test_the_proposal_sampler_crowds_the_field_samples_where_the_proposals_see_density():
    class Slab(torch.nn.Module):  # opaque for |x| < 0.25: along the rays below, t in (3.75, 4.25)
        def density(self, points):
            return 100.0 * (points[..., 0].abs() < 0.25).float()

    space = SceneSpace(2.0, 6.0)
    rays = space.rays(torch.tensor([[-4.0, 0.0, 0.0]]).expand(64, 3), torch.tensor([[1.0, 0.0, 0.0]]).expand(64, 3))
    sampler = ProposalSampler([Slab(), Slab()], proposal_samples=(64, 32), field_samples=32, anneal_steps=10)
    sampler.update(100, None)  # annealing done: the weights as they are
    samples = sampler.sample(rays, space, None, perturb=True)
    assert_packed_in_range(samples, 2.0, 6.0)
    mids = 0.5 * (samples.t_starts + samples.t_ends)
    assert ((mids > 3.6) & (mids < 4.0)).float().mean() > 0.8  # where the ray meets the slab, not spread over 2..6
    sampler.update(0, None)  # at step 0 the proposal weights are annealed flat: intervals spread along the ray
    flat = sampler.sample(rays, space, None, perturb=True)
    flat_mids = 0.5 * (flat.t_starts + flat.t_ends)
    assert ((flat_mids > 3.6) & (flat_mids < 4.0)).float().mean() < 0.3


def test_a_baked_proposal_network_matches_the_network_at_its_vertices_and_is_used_in_evaluation_only(monkeypatch):
    torch.manual_seed(0)
    network = small_density_field()
    with torch.no_grad():
        network.encoding.table.uniform_(-1.0, 1.0)  # a density that varies over the box
    baked = network.bake(resolution=8)
    vertices = torch.tensor([[0, 0, 0], [8, 0, 0], [0, 8, 0], [0, 0, 8], [3, 5, 7], [8, 8, 8]]) / 8.0 * 3.0 - 1.5
    with torch.no_grad():
        assert torch.allclose(baked.density(vertices), network.density(vertices), rtol=1e-4)
        # between the vertices: the log-density interpolated, so inside the range of the cell's corners
        cell_corners = torch.tensor([[dx, dy, dz] for dx in (3, 4) for dy in (5, 6) for dz in (1, 2)]) / 8.0 * 3.0 - 1.5
        corner_densities = network.density(cell_corners)
        inside = baked.density(cell_corners.mean(0, keepdim=True))
        assert corner_densities.min() <= inside <= corner_densities.max()
        assert float(baked.density(torch.tensor([[1.6, 0.0, 0.0]]))) == 0.0  # outside the box
        # the one-level hash grid an Apple GPU before torch 2.9 falls back to (no 3D grid_sample) reads the same
        points = torch.cat([torch.rand(256, 3) * 3.0 - 1.5, torch.tensor([[1.6, 0.0, 0.0]])])
        with_grid_sample = baked.density(points)
        monkeypatch.setattr(grid_module, "has_grid_sample_3d", lambda device: False)
        assert torch.allclose(baked.density(points), with_grid_sample, rtol=1e-5)
        assert float(with_grid_sample[-1]) == 0.0
        monkeypatch.undo()

    space = SceneSpace(2.0, 6.0)
    rays = camera_rays(space)
    sampler = ProposalSampler([network, small_density_field()], proposal_samples=(32, 16), field_samples=12, bake_resolution=16)
    sampler.update(10_000, None)
    with torch.no_grad():  # a module still training (the live viewer renders between steps): nothing baked
        sampler.sample(rays, space, None, perturb=False)
    assert not sampler._bakes
    sampler.eval()
    with torch.no_grad():
        evaluated = sampler.sample(rays, space, None, perturb=False)
    assert_packed_in_range(evaluated, 2.0, 6.0)
    assert set(sampler._bakes) == {0, 1}
    first = sampler.baked(0)
    assert sampler.baked(0) is first  # kept while the weights stay
    with torch.no_grad():
        network.encoding.table.mul_(2.0)
    assert sampler.baked(0) is not first  # made again once they change
    sampler._bakes.clear()
    sampler.train()
    sampler.sample(rays, space, None, perturb=True)  # training: the networks themselves, nothing baked
    assert not sampler._bakes


def test_the_interlevel_loss_is_zero_when_the_proposal_bounds_the_weights_and_positive_otherwise():
    edges = torch.linspace(0.0, 1.0, 9)[None]  # 8 fine intervals
    weights = torch.tensor([[0.0, 0.1, 0.4, 0.3, 0.1, 0.0, 0.0, 0.0]])
    coarse_edges = torch.linspace(0.0, 1.0, 5)[None]  # 4 coarse intervals, each over two fine ones
    bounding = torch.tensor([[0.1, 0.7, 0.1, 0.0]])  # each coarse weight >= the fine weights inside it
    assert float(interlevel_loss(edges, weights, coarse_edges, bounding)) == pytest.approx(0.0, abs=1e-10)
    short = torch.tensor([[0.1, 0.2, 0.1, 0.0]])  # the 0.4 in [0.25, 0.375] is not bounded by its coarse bin's 0.2
    # (the 0.3 in [0.375, 0.5] touches the next coarse bin at 0.5, so its bound is 0.2 + 0.1: closed intervals, as nerfstudio's)
    expected = (0.4 - 0.2) ** 2 / 0.4
    assert float(interlevel_loss(edges, weights, coarse_edges, short)) == pytest.approx(expected, rel=1e-5)
    # gradients reach the proposal's weights only
    short = short.clone().requires_grad_(True)
    detached = weights.clone().requires_grad_(True)
    interlevel_loss(edges, detached, coarse_edges, short).backward()
    assert short.grad is not None and detached.grad is None


def test_the_linear_time_distortion_loss_equals_its_quadratic_definition():
    generator = torch.Generator().manual_seed(0)
    edges = torch.sort(torch.rand(50, 33, generator=generator, dtype=torch.float64), dim=-1).values
    weights = torch.rand(50, 32, generator=generator, dtype=torch.float64)
    weights = weights / weights.sum(-1, keepdim=True) * torch.rand(50, 1, generator=generator, dtype=torch.float64)
    mids, widths = 0.5 * (edges[:, 1:] + edges[:, :-1]), edges[:, 1:] - edges[:, :-1]
    quadratic = (weights[:, :, None] * weights[:, None, :] * (mids[:, :, None] - mids[:, None, :]).abs()).sum((1, 2))
    quadratic = (quadratic + (weights**2 * widths).sum(-1) / 3).mean()
    torch.testing.assert_close(distortion_loss(edges, weights), quadratic)


class ConstantField(torch.nn.Module):
    """One learnt density and colour everywhere."""

    def __init__(self):
        super().__init__()
        self.sigma, self.colour = torch.nn.Parameter(torch.tensor(2.0)), torch.nn.Parameter(torch.tensor([0.2, 0.5, 0.7]))

    def forward(self, points, viewdirs):
        return {"density": self.sigma.expand(points.shape[0]), "rgb": self.colour.expand(points.shape[0], 3)}

    def density(self, points):
        return self.sigma.expand(points.shape[:-1])


@pytest.mark.parametrize("t_mid, scale", [(0.5, 0.25), (0.25, 0.0625), (1.5, 1.0)])
def test_gradient_scaling_scales_the_gradients_of_near_samples_by_the_squared_distance(t_mid, scale):
    space = SceneSpace(near=0.0, far=4.0)
    rays = space.rays(torch.zeros(3, 3), torch.nn.functional.normalize(torch.randn(3, 3), dim=-1))
    samples = RaySamples.from_edges(torch.tensor([[t_mid - 0.1, t_mid + 0.1]]).expand(3, 2).contiguous())
    grads, values = [], []
    for distance in (0.0, 1.0):
        field = ConstantField()
        out = RoundsRenderer(early_stop_eps=0.0, gradient_scaling_distance=distance)(field, rays, samples, space)
        out["rgb"].sum().backward()
        grads.append(torch.cat([field.sigma.grad[None], field.colour.grad]))
        values.append(out["rgb"].detach())
    torch.testing.assert_close(values[1], values[0])  # the picture is the same; only the gradients shrink
    torch.testing.assert_close(grads[1], grads[0] * scale)
