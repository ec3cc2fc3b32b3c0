"""Scene contraction (Mip-NeRF 360, max-norm), as the scene space applies it before a field."""

import math

import pytest
import torch

from nerf_lightning.geometry.contraction import Contraction, contract, uncontract
from nerf_lightning.geometry.space import SceneSpace


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


def test_the_contraction_object_maps_all_of_space_into_its_bounds_and_back():
    contraction = Contraction()
    points = torch.randn(300, 3, dtype=torch.float64) * 10.0 ** torch.randint(-1, 9, (300, 1))
    inside = contraction(points)
    assert bool((inside.abs() < contraction.bounds[3]).all())
    torch.testing.assert_close(contraction.inverse(inside[points.abs().amax(-1) < 1e5]), points[points.abs().amax(-1) < 1e5], rtol=1e-6, atol=1e-9)
    # a point far out along +x lands on the cube's +x face
    torch.testing.assert_close(contraction(torch.tensor([1e9, 0.0, 0.5])), torch.tensor([2.0, 0.0, 0.0]), atol=1e-8, rtol=0)


def test_a_contracted_scene_space_feeds_a_grid_field_contracted_points_with_density_everywhere():
    from nerf_lightning.fields import GridField, HashGridEncoding

    points = torch.tensor([[0.0, 0.0, 0.0], [5.0, 0.0, 0.0], [0.0, -40.0, 3.0]])
    encoding = dict(n_levels=2, log2_table_size=10, base_resolution=4, max_resolution=8)
    torch.manual_seed(0)
    bounded = GridField(aabb=[-1, -1, -1, 1, 1, 1], encoding=HashGridEncoding(**encoding))
    unbounded = GridField(aabb=list(Contraction.bounds), encoding=HashGridEncoding(**encoding))
    space = SceneSpace(0.05, 1e3, contraction=Contraction())
    with torch.no_grad():
        assert bool((bounded.density(points)[1:] == 0).all()) and float(bounded.density(points)[0]) > 0
        assert bool((unbounded.density(space.to_field(points)) > 0).all())
        assert math.isfinite(float(unbounded.density(space.to_field(torch.tensor([[1e12, 0.0, 0.0]])))[0]))
    space.check_box(unbounded.aabb, "model.field.aabb")
    with pytest.raises(ValueError, match=r"model.field.aabb is .* a contracted scene"):
        space.check_box(bounded.aabb, "model.field.aabb")
