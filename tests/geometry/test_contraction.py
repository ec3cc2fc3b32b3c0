"""Scene contraction (Mip-NeRF 360, max-norm) and the map from the world to a grid's unit cube."""

import math

import pytest
import torch

from nerf_lightning.geometry.contraction import contract, uncontract, unit_to_world, world_to_unit

AABB = torch.tensor([-1.0, -2.0, 0.0, 3.0, 2.0, 1.0])


def test_contract_keeps_the_unit_box_and_squeezes_the_rest_below_2():
    generator = torch.Generator().manual_seed(0)
    inside = torch.rand(1000, 3, generator=generator, dtype=torch.float64) * 2 - 1
    torch.testing.assert_close(contract(inside), inside)
    far = torch.randn(1000, 3, generator=generator, dtype=torch.float64) * 10.0 ** torch.randint(0, 6, (1000, 1), generator=generator)
    far = far[far.abs().amax(-1) > 1.0]
    squeezed = contract(far).abs().amax(-1)
    assert bool(((squeezed > 1.0) & (squeezed < 2.0)).all())
    # the max-norm becomes 2 - 1/|x|: monotone along a ray from the centre, continuous at the box's surface
    radii = torch.tensor([0.5, 1.0, 1.0 + 1e-9, 2.0, 10.0, 1e6], dtype=torch.float64)
    direction = torch.tensor([0.3, -1.0, 0.2], dtype=torch.float64)
    norms = contract(radii[:, None] * direction).abs().amax(-1)
    torch.testing.assert_close(norms, torch.tensor([0.5, 1.0, 1.0, 1.5, 1.9, 2.0 - 1e-6], dtype=torch.float64), atol=1e-8, rtol=0)
    # directions are kept
    torch.testing.assert_close(torch.nn.functional.normalize(contract(far), dim=-1), torch.nn.functional.normalize(far, dim=-1))


def test_uncontract_inverts_contract():
    points = torch.randn(500, 3, dtype=torch.float64) * torch.logspace(-1, 3, 500, dtype=torch.float64)[:, None]
    torch.testing.assert_close(uncontract(contract(points)), points, rtol=1e-6, atol=1e-9)


@pytest.mark.parametrize("contracted", [False, True])
def test_world_to_unit_and_back(contracted):
    points = torch.randn(300, 3, dtype=torch.float64) * 5.0
    unit = world_to_unit(points, AABB.double(), contracted)
    torch.testing.assert_close(unit_to_world(unit, AABB.double(), contracted), points, rtol=1e-6, atol=1e-9)
    corners_low, corners_high = world_to_unit(AABB[:3], AABB, contracted), world_to_unit(AABB[3:], AABB, contracted)
    low, high = (0.25, 0.75) if contracted else (0.0, 1.0)
    torch.testing.assert_close(corners_low, torch.full((3,), low))
    torch.testing.assert_close(corners_high, torch.full((3,), high))
    if contracted:  # all of space lands inside the cube
        assert bool(((unit >= 0) & (unit <= 1)).all())
        # a point far out along +x (the box's centre is (1, 0, 0.5)) lands on the cube's +x face, centred
        torch.testing.assert_close(world_to_unit(torch.tensor([1e9, 0.0, 0.5]), AABB, True), torch.tensor([1.0, 0.5, 0.5]))


def test_a_contracted_grid_field_has_density_everywhere_a_bounded_one_only_in_its_box():
    from nerf_lightning.fields import HashGridField

    points = torch.tensor([[0.0, 0.0, 0.0], [5.0, 0.0, 0.0], [0.0, -40.0, 3.0]])
    kwargs = dict(aabb=[-1, -1, -1, 1, 1, 1], n_levels=2, log2_table_size=10, base_resolution=4, max_resolution=8)
    torch.manual_seed(0)
    bounded, unbounded = HashGridField(**kwargs), HashGridField(**kwargs, contracted=True)
    with torch.no_grad():
        assert bool((bounded.density(points)[1:] == 0).all()) and float(bounded.density(points)[0]) > 0
        assert bool((unbounded.density(points) > 0).all())
        assert math.isfinite(float(unbounded.density(torch.tensor([[1e12, 0.0, 0.0]]))[0]))
