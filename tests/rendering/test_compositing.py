"""Compositing weights: from density and from alpha, dense and packed, in one pass and in rounds."""

import pytest
import torch

from nerf_lightning.rendering import (
    weights_from_alpha,
    weights_from_alpha_packed,
    weights_from_optical_depth,
    weights_from_optical_depth_packed,
)


def random_optical_depth(*shape, seed=0):
    generator = torch.Generator().manual_seed(seed)
    # mostly thin samples with a few nearly opaque ones, as along a ray that hits a surface
    return torch.rand(*shape, generator=generator, dtype=torch.float64) ** 3 * 4


def loop_reference(alpha):
    """(N, S) -> (N, S) weights and (N,) transmittance after, one sample at a time: T *= 1 - alpha."""
    transmittance = torch.ones_like(alpha[:, 0])
    weights = []
    for i in range(alpha.shape[1]):
        weights.append(transmittance * alpha[:, i])
        transmittance = transmittance * (1 - alpha[:, i])
    return torch.stack(weights, dim=1), transmittance


def test_from_density_equals_from_alpha():
    optical_depth = random_optical_depth(20, 12)
    from_density = weights_from_optical_depth(optical_depth)
    from_alpha = weights_from_alpha(1 - torch.exp(-optical_depth))
    for got, expected in zip(from_alpha, from_density):
        torch.testing.assert_close(got, expected)
    torch.testing.assert_close(from_density.transmittance[:, 0], torch.ones(20, dtype=torch.float64))
    torch.testing.assert_close(from_density.transmittance_after, torch.exp(-optical_depth.sum(-1)))


def test_from_alpha_is_the_product_of_one_minus_alpha():
    alpha = torch.rand(6, 9, generator=torch.Generator().manual_seed(1), dtype=torch.float64) * 0.999
    out = weights_from_alpha(alpha)
    weights, after = loop_reference(alpha)
    torch.testing.assert_close(out.weights, weights)
    torch.testing.assert_close(out.transmittance_after, after)
    torch.testing.assert_close(out.weights, out.transmittance * alpha, rtol=0, atol=0)  # w_i = T_i alpha_i exactly
    assert out.alpha is alpha


@pytest.mark.parametrize("from_alpha", [False, True])
def test_packed_equals_dense_on_rays_of_unequal_sample_counts(from_alpha):
    optical_depth = random_optical_depth(5, 7, seed=2)
    counts = torch.tensor([7, 0, 3, 1, 0])  # rays 1 and 4 without samples
    keep = torch.arange(7) < counts[:, None]
    ray_indices = keep.nonzero()[:, 0]
    before = torch.tensor([1.0, 0.5, 0.9, 0.25, 1.0], dtype=torch.float64)
    values = 1 - torch.exp(-optical_depth) if from_alpha else optical_depth
    dense_fn = weights_from_alpha if from_alpha else weights_from_optical_depth
    packed_fn = weights_from_alpha_packed if from_alpha else weights_from_optical_depth_packed
    packed = packed_fn(values[keep], ray_indices, 5, before)
    for ray in range(5):
        dense = dense_fn(values[ray : ray + 1, : counts[ray]], before[ray : ray + 1])
        in_ray = ray_indices == ray
        torch.testing.assert_close(packed.weights[in_ray], dense.weights[0])
        torch.testing.assert_close(packed.transmittance[in_ray], dense.transmittance[0])
        torch.testing.assert_close(packed.transmittance_after[ray], dense.transmittance_after[0])
    torch.testing.assert_close(packed.transmittance_after[counts == 0], before[counts == 0])  # nothing crossed
    empty = packed_fn(values[:0, 0], ray_indices[:0], 3)
    assert empty.weights.shape == (0,) and torch.equal(empty.transmittance_after, torch.ones(3, dtype=torch.float64))


@pytest.mark.parametrize("from_alpha", [False, True])
def test_transmittance_carried_over_two_rounds_equals_one_pass(from_alpha):
    optical_depth = random_optical_depth(8, 10, seed=3)
    values = 1 - torch.exp(-optical_depth) if from_alpha else optical_depth
    composite = weights_from_alpha if from_alpha else weights_from_optical_depth
    whole = composite(values)
    first = composite(values[:, :4])
    second = composite(values[:, 4:], first.transmittance_after)
    torch.testing.assert_close(torch.cat([first.weights, second.weights], dim=1), whole.weights)
    torch.testing.assert_close(torch.cat([first.transmittance, second.transmittance], dim=1), whole.transmittance)
    torch.testing.assert_close(second.transmittance_after, whole.transmittance_after)

    # packed, with the rounds splitting the rays' samples unevenly
    ray_indices = torch.arange(8).repeat_interleave(10)
    in_first = (torch.arange(10) < torch.arange(8)[:, None] % 5).reshape(-1)  # ray r's first r % 5 samples
    packed_fn = weights_from_alpha_packed if from_alpha else weights_from_optical_depth_packed
    first = packed_fn(values.reshape(-1)[in_first], ray_indices[in_first], 8)
    second = packed_fn(values.reshape(-1)[~in_first], ray_indices[~in_first], 8, first.transmittance_after)
    torch.testing.assert_close(first.weights, whole.weights.reshape(-1)[in_first])
    torch.testing.assert_close(second.weights, whole.weights.reshape(-1)[~in_first])
    torch.testing.assert_close(second.transmittance_after, whole.transmittance_after)


def test_weights_sum_to_the_accumulation_at_most_one():
    optical_depth = torch.cat([random_optical_depth(50, 32, seed=4), torch.full((1, 32), 50.0, dtype=torch.float64)])
    for out in (weights_from_optical_depth(optical_depth), weights_from_alpha(1 - torch.exp(-optical_depth.clamp(max=6.0)))):
        accumulation = out.weights.sum(-1)
        torch.testing.assert_close(accumulation, 1 - out.transmittance_after)
        assert (out.weights >= 0).all() and (accumulation <= 1 + 1e-12).all()  # opaque rays: 1 up to the sum's rounding
    torch.testing.assert_close(weights_from_optical_depth(optical_depth).weights[-1].sum(), torch.tensor(1.0, dtype=torch.float64))


def test_gradients_from_alpha_match_the_plain_loop():
    generator = torch.Generator().manual_seed(5)
    alpha = (torch.rand(3, 5, generator=generator, dtype=torch.float64) * 0.95).requires_grad_()
    upstream_weights = torch.randn(3, 5, generator=generator, dtype=torch.float64)
    upstream_after = torch.randn(3, generator=generator, dtype=torch.float64)

    def loss(out_weights, out_after):
        return (out_weights * upstream_weights).sum() + (out_after * upstream_after).sum()

    out = weights_from_alpha(alpha)
    (got,) = torch.autograd.grad(loss(out.weights, out.transmittance_after), alpha)
    (expected,) = torch.autograd.grad(loss(*loop_reference(alpha)), alpha)
    torch.testing.assert_close(got, expected)

    before = torch.rand(3, generator=generator, dtype=torch.float64).requires_grad_()
    ray_indices = torch.tensor([0, 0, 0, 2, 2])

    def dense(alpha, before):
        out = weights_from_alpha(alpha, before)
        return out.weights, out.transmittance, out.transmittance_after

    def packed(alpha, before):
        out = weights_from_alpha_packed(alpha, ray_indices, 3, before)
        return out.weights, out.transmittance, out.transmittance_after

    assert torch.autograd.gradcheck(dense, (alpha, before))
    assert torch.autograd.gradcheck(packed, (alpha[0].detach().requires_grad_(), before))


@pytest.mark.parametrize("packed", [False, True])
def test_opaque_splats_clamped_at_0999_stay_finite(packed):
    alpha = torch.full((4, 200), 0.999, requires_grad=True)  # float32: the transmittance underflows to 0
    if packed:
        out = weights_from_alpha_packed(alpha.reshape(-1), torch.arange(4).repeat_interleave(200), 4)
    else:
        out = weights_from_alpha(alpha)
    out.weights.sum().backward()
    assert torch.isfinite(out.weights).all() and torch.isfinite(alpha.grad).all()
    torch.testing.assert_close(out.weights.reshape(4, 200)[:, 0], torch.full((4,), 0.999))
    torch.testing.assert_close(out.weights.sum(), torch.tensor(4.0))


def test_shapes_are_checked_at_the_boundary():
    with pytest.raises(ValueError, match=r"transmittance_before of shape \(\.\.\.,\) = \(2,\)"):
        weights_from_optical_depth(torch.ones(2, 3), torch.ones(3))
    with pytest.raises(ValueError, match=r"ray_indices \(M,\)"):
        weights_from_alpha_packed(torch.full((4,), 0.5), torch.zeros(3, dtype=torch.long), 1)
