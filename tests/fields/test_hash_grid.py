"""The hash-grid encoding against a plain-loop reference, the spherical harmonics, and the hash-grid field."""

import math

import pytest
import torch

from nerf_lightning.fields import GridField, HashGridEncoding, SphericalHarmonicsEncoding, TensorVMEncoding
from nerf_lightning.fields.hash_grid import encode_reference, level_resolutions


def hash_grid_field(aabb, **encoding) -> GridField:
    """The hash-grid field as the configs build it: GridField(encoding=HashGridEncoding)."""
    return GridField(aabb=aabb, encoding=HashGridEncoding(**encoding))


def small_encoding(**overrides) -> HashGridEncoding:
    """4 levels of 4, 10, 25, 64 cells with tables of at most 2^11 rows: levels 0-1 dense ((N+1)^3 <= 2048), 2-3 hashed."""
    options = dict(n_levels=4, features_per_level=2, log2_table_size=11, base_resolution=4, max_resolution=64)
    options.update(overrides)
    encoding = HashGridEncoding(**options)
    with torch.no_grad():
        encoding.table.normal_(generator=torch.Generator().manual_seed(0))
    return encoding


def reference_encoding(encoding: HashGridEncoding, point: list[float]) -> list[float]:
    """The encoding of one point, written with plain Python loops and integers from the paper's definition."""
    table_size = encoding.table_size
    out = []
    offset = 0
    for resolution in level_resolutions(encoding.n_levels, int(encoding.resolutions[0]), int(encoding.resolutions[-1])):
        side = resolution + 1
        rows_in_level = min(side**3, table_size)
        scaled = [min(max(c, 0.0), 1.0) * resolution for c in point]
        lower = [min(int(math.floor(c)), resolution - 1) for c in scaled]
        feature = [0.0] * encoding.features_per_level
        for dx in (0, 1):
            for dy in (0, 1):
                for dz in (0, 1):
                    x, y, z = lower[0] + dx, lower[1] + dy, lower[2] + dz
                    if side**3 <= table_size:
                        row = x + y * side + z * side * side
                    else:
                        row = ((x * 1) ^ (y * 2654435761) ^ (z * 805459861)) % table_size
                    weight = 1.0
                    for c, d, low in zip(scaled, (dx, dy, dz), lower):
                        weight *= (c - low) if d else 1.0 - (c - low)
                    for f in range(encoding.features_per_level):
                        feature[f] += weight * float(encoding.table.detach()[offset + row, f])
        out.extend(feature)
        offset += rows_in_level
    return out


def test_level_resolutions_grow_geometrically_from_base_to_max():
    assert level_resolutions(4, 4, 64) == [4, 10, 25, 64]
    assert level_resolutions(16, 16, 2048)[0] == 16 and level_resolutions(16, 16, 2048)[-1] == 2048


def test_hash_encoding_equals_the_plain_loop_reference():
    encoding = small_encoding()
    assert encoding.hashed.tolist() == [False, False, True, True]
    points = torch.rand(40, 3, generator=torch.Generator().manual_seed(1), dtype=torch.float64)
    points[0] = torch.tensor([1.0, 1.0, 1.0])  # the far corner: the last cell, not one past it
    points[1] = torch.tensor([0.0, 0.5, 1.0])
    encoding = encoding.double()
    expected = torch.tensor([reference_encoding(encoding, p.tolist()) for p in points], dtype=torch.float64)
    # encode_reference, forward_reference (which calls it) and forward (with gradients here: a fast path)
    reference = encode_reference(points, *encoding.reference_inputs())
    torch.testing.assert_close(reference, expected, rtol=1e-9, atol=1e-9)
    torch.testing.assert_close(encoding.forward_reference(points.reshape(4, 10, 3)), expected.reshape(4, 10, 8), rtol=1e-9, atol=1e-9)
    got = encoding(points)
    assert got.shape == (40, 8)
    torch.testing.assert_close(got, expected, rtol=1e-9, atol=1e-9)


def test_rows_in_int32_where_no_hash_product_can_overflow_and_in_int64_otherwise():
    # int32: the primes are reduced modulo T, which keeps the rows (the reference above hashes with the full primes)
    assert small_encoding().index_dtype == torch.int32
    # (2048 + 1) * (2^21 - 1) > 2^31: int64, and still the reference's rows
    encoding = HashGridEncoding(n_levels=2, log2_table_size=21, base_resolution=16, max_resolution=2048).double()
    assert encoding.index_dtype == torch.int64
    with torch.no_grad():
        encoding.table.uniform_(-1.0, 1.0)
    points = torch.rand(20, 3, generator=torch.Generator().manual_seed(2), dtype=torch.float64)
    expected = torch.tensor([reference_encoding(encoding, p.tolist()) for p in points], dtype=torch.float64)
    torch.testing.assert_close(encoding(points), expected, rtol=1e-9, atol=1e-9)


def test_hash_encoding_is_continuous_across_cell_borders():
    encoding = small_encoding().double()
    # a point on a border of the finest level's cells (x = 32/64), approached from both sides
    border = torch.tensor([[0.5, 0.3141, 0.7071]], dtype=torch.float64)
    for axis in range(3):
        step = torch.zeros(1, 3, dtype=torch.float64)
        step[0, axis] = 1e-9
        jump = (encoding(border + step) - encoding(border - step)).abs().max()
        assert jump < 1e-6
    # while a step across a whole fine cell changes it by the table's scale
    assert (encoding(border + 1 / 64) - encoding(border)).abs().max() > 1e-2


def test_hash_encoding_passes_gradients_to_its_table():
    encoding = small_encoding().double()
    points = torch.rand(5, 3, generator=torch.Generator().manual_seed(2), dtype=torch.float64)
    encoding(points).square().sum().backward()
    touched = (encoding.table.grad.abs().sum(dim=-1) > 0).sum()
    assert 0 < touched <= 5 * 4 * 8  # at most 8 vertices a level a point
    encoding = small_encoding(n_levels=2, log2_table_size=6, base_resolution=2, max_resolution=8).double()  # 27 + 64 rows
    table = encoding.table.detach().clone().requires_grad_(True)
    # gradcheck through the gather: analytic and numerical gradients with respect to the table agree
    assert torch.autograd.gradcheck(lambda t: torch.func.functional_call(encoding, {"table": t}, (points,)), (table,))


def test_hash_encoding_gradients_with_respect_to_points_are_the_numerical_ones():
    """Points carry gradients when rays do (camera refinement): through the trilinear weights, for rows of two (summed
    as complex numbers on a CPU) and of three (summed as real rows)."""
    for width in (2, 3):
        encoding = small_encoding(features_per_level=width).double()
        points = torch.rand(6, 3, generator=torch.Generator().manual_seed(4), dtype=torch.float64).requires_grad_(True)
        assert torch.autograd.gradcheck(encoding, (points,))


def test_hash_encoding_sums_corners_alike_with_and_without_gradients():
    """In float32 on a CPU, training sums the corners of rows of two as complex numbers, evaluation as real rows
    (``compile_evaluation=False``) or corner by corner (:func:`encode_reference`, compiled where it can be): the
    same features to float32 rounding."""
    encoding = small_encoding()
    points = torch.rand(300, 3, generator=torch.Generator().manual_seed(5))
    trained = encoding(points)
    assert trained.requires_grad
    encoding.eval()
    for compiled in (False, True):
        encoding.compile_evaluation = compiled
        with torch.no_grad():
            evaluated = encoding(points)
        assert torch.allclose(trained, evaluated, atol=1e-6, rtol=1e-5), compiled


def test_hash_encoding_keeps_leading_axes_and_rejects_wrong_widths():
    encoding = small_encoding()
    for forward in (encoding, encoding.forward_reference):
        assert forward(torch.rand(2, 7, 3)).shape == (2, 7, 8)
        assert forward(torch.zeros(0, 3)).shape == (0, 8)
        with pytest.raises(ValueError, match=r"\(\.\.\., 3\)"):
            forward(torch.rand(4, 2))


def test_hash_encoding_saves_only_its_table():
    """Checkpoints hold the table alone (the levels are rebuilt from the arguments): its key must not change."""
    assert list(small_encoding().state_dict()) == ["table"]


def test_spherical_harmonics_are_orthonormal_on_the_sphere():
    directions = torch.randn(400_000, 3, generator=torch.Generator().manual_seed(0), dtype=torch.float64)
    directions = directions / directions.norm(dim=-1, keepdim=True)
    basis = SphericalHarmonicsEncoding(4)(directions)  # (M, 16)
    gram = 4 * math.pi * basis.T @ basis / len(directions)  # Monte Carlo integral of Y_i Y_j over the sphere
    torch.testing.assert_close(gram, torch.eye(16, dtype=torch.float64), atol=0.03, rtol=0)
    assert SphericalHarmonicsEncoding(2)(directions[:3]).shape == (3, 4)


def test_hash_grid_field_outputs_and_is_empty_outside_its_box():
    field = hash_grid_field(aabb=[-1, -1, -1, 1, 1, 1], n_levels=4, log2_table_size=12, base_resolution=4, max_resolution=32)
    points = torch.tensor([[0.0, 0.0, 0.0], [0.5, -0.5, 0.2], [1.5, 0.0, 0.0], [0.0, 0.0, -3.0]])
    directions = torch.nn.functional.normalize(torch.randn(4, 3), dim=-1)
    out = field(points, directions)
    assert out["rgb"].shape == (4, 3) and out["density"].shape == (4,)
    assert ((out["rgb"] > 0) & (out["rgb"] < 1)).all()
    assert (out["density"][:2] > 0).all() and (out["density"][2:] == 0).all()
    out["density"].sum().backward()
    assert field.encoding.table.grad.abs().sum() > 0
    with pytest.raises(ValueError, match="aabb"):
        hash_grid_field(aabb=[1, 1, 1, -1, -1, -1])


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA device")
def test_hash_grid_field_gives_the_same_result_on_cuda():
    field = hash_grid_field(aabb=[-1, -1, -1, 1, 1, 1], n_levels=8, log2_table_size=14, max_resolution=256)
    points = torch.rand(1000, 3) * 2 - 1
    directions = torch.nn.functional.normalize(torch.randn(1000, 3), dim=-1)
    on_cpu = field(points, directions)
    on_cuda = field.cuda()(points.cuda(), directions.cuda())
    for key in ("rgb", "density"):
        torch.testing.assert_close(on_cuda[key].cpu(), on_cpu[key], atol=1e-4, rtol=1e-4)


def test_factorised_grid_encoding_interpolates_its_factors():
    encoding = TensorVMEncoding(resolution=5, components=2)
    # at a grid vertex the feature of axis x, component c is plane[0, c, row(z), column(y)] * line[0, c, row(x)]
    point = torch.tensor([[0.25, 0.5, 1.0]])  # vertices x = 1, y = 2, z = 4 of 0..4
    got = encoding(point)[0]
    expected_x = encoding.planes[0, :, 4, 2] * encoding.lines[0, :, 1, 0]
    expected_z = encoding.planes[2, :, 2, 1] * encoding.lines[2, :, 4, 0]
    torch.testing.assert_close(got[:2], expected_x)
    torch.testing.assert_close(got[4:], expected_z)
    # linear along a line between vertices (the plane factor fixed): halfway gives the mean
    a, b = encoding(torch.tensor([[0.0, 0.5, 0.5]])), encoding(torch.tensor([[0.25, 0.5, 0.5]]))
    torch.testing.assert_close(encoding(torch.tensor([[0.125, 0.5, 0.5]]))[0, :2], (a + b)[0, :2] / 2)
    encoding(torch.rand(10, 3)).sum().backward()
    assert encoding.planes.grad.abs().sum() > 0 and encoding.lines.grad.abs().sum() > 0
    assert GridField([-1, -1, -1, 1, 1, 1], encoding)(torch.zeros(4, 3), torch.eye(3)[[0, 1, 2, 0]])["rgb"].shape == (4, 3)


def test_the_gather_interpolation_for_apple_gpus_equals_grid_sample_and_its_gradient():
    from nerf_lightning.fields.tensorf import bilinear_gather

    generator = torch.Generator().manual_seed(0)
    for shape in ((3, 5, 7, 6), (3, 5, 9, 1)):  # the planes, and the lines (one column)
        grids = torch.randn(*shape, generator=generator, dtype=torch.float64, requires_grad=True)
        xy = torch.rand(3, 200, 2, generator=generator, dtype=torch.float64) * 2 - 1
        if shape[-1] == 1:
            xy[..., 0] = 0.0
        expected = torch.nn.functional.grid_sample(grids, xy[:, :, None], mode="bilinear", align_corners=True)
        got = bilinear_gather(grids, xy)
        torch.testing.assert_close(got, expected)
        weights = torch.randn(expected.shape, generator=generator, dtype=torch.float64)
        (expected_grad,) = torch.autograd.grad((expected * weights).sum(), grids)
        (got_grad,) = torch.autograd.grad((got * weights).sum(), grids)
        torch.testing.assert_close(got_grad, expected_grad)
