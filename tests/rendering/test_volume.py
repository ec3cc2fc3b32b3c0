"""Volume rendering against closed forms."""

import math

import torch

from nerf_lightning.rendering import composite, render_weights, sample_pdf, transmittance


def deltas_of(t: torch.Tensor, last: float) -> torch.Tensor:
    """(N, S) sorted distances -> (N, S) interval lengths, the last one ``last``."""
    return torch.cat([t[..., 1:] - t[..., :-1], torch.full_like(t[..., :1], last)], dim=-1)


def test_constant_slab_transmittance_is_beer_lambert():
    sigma, length, steps = 0.7, 3.0, 300
    deltas = torch.full((1, steps), length / steps, dtype=torch.float64)
    density = torch.full_like(deltas, sigma)
    travelled = torch.arange(steps, dtype=torch.float64) * length / steps
    torch.testing.assert_close(transmittance(density, deltas)[0], torch.exp(-sigma * travelled))
    # what gets through the whole slab: 1 - accumulation = exp(-sigma s)
    accumulation = render_weights(density, deltas).sum(-1)
    torch.testing.assert_close(1.0 - accumulation, torch.tensor([math.exp(-sigma * length)], dtype=torch.float64))


def test_a_single_opaque_sample_takes_all_the_colour_and_the_depth():
    density = torch.tensor([[0.0, 0.0, 1e4, 0.0]])
    t = torch.tensor([[1.0, 2.0, 3.0, 4.0]])
    rgb = torch.tensor([[[1.0, 0, 0], [0, 1.0, 0], [0.2, 0.4, 0.6], [0, 0, 1.0]]])
    out = composite(rgb, density, t, torch.ones_like(t), background=torch.ones(3))
    torch.testing.assert_close(out["weights"], torch.tensor([[0.0, 0.0, 1.0, 0.0]]))
    torch.testing.assert_close(out["rgb"], torch.tensor([[0.2, 0.4, 0.6]]))
    torch.testing.assert_close(out["depth"], torch.tensor([3.0]))
    torch.testing.assert_close(out["accumulation"], torch.tensor([1.0]))


def test_empty_space_shows_the_background():
    t = torch.linspace(2, 6, 8).expand(5, 8)
    out = composite(torch.rand(5, 8, 3), torch.zeros(5, 8), t, deltas_of(t, 0.5), background=torch.tensor([0.1, 0.2, 0.3]))
    torch.testing.assert_close(out["rgb"], torch.tensor([[0.1, 0.2, 0.3]] * 5))
    torch.testing.assert_close(out["accumulation"], torch.zeros(5))


def test_weights_sum_to_the_accumulation_and_colour_is_their_mean():
    generator = torch.Generator().manual_seed(0)
    density = torch.rand(100, 32, generator=generator) * 3
    t = torch.sort(torch.rand(100, 32, generator=generator) * 4 + 2, dim=-1).values
    deltas = deltas_of(t, 0.1)
    rgb = torch.rand(100, 32, 3, generator=generator)
    out = composite(rgb, density, t, deltas, background=torch.zeros(3))
    torch.testing.assert_close(out["weights"].sum(-1), out["accumulation"])
    assert (out["accumulation"] <= 1).all() and (out["weights"] >= 0).all()
    torch.testing.assert_close(out["rgb"], (out["weights"][..., None] * rgb).sum(1))
    # the depth is the weights' mean of t, so it lies within the samples
    assert ((out["depth"] >= t[:, 0]) & (out["depth"] <= t[:, -1])).all()


def test_gradients_match_finite_differences_in_float64():
    generator = torch.Generator().manual_seed(1)
    density = (torch.rand(3, 6, generator=generator, dtype=torch.float64) * 2).requires_grad_()
    rgb = torch.rand(3, 6, 3, generator=generator, dtype=torch.float64).requires_grad_()
    t = torch.sort(torch.rand(3, 6, generator=generator, dtype=torch.float64) * 4 + 2, dim=-1).values
    deltas = deltas_of(t, 0.2)
    background = torch.tensor([1.0, 0.5, 0.0], dtype=torch.float64)

    def rendered(density, rgb):
        out = composite(rgb, density, t, deltas, background)
        return out["rgb"], out["depth"], out["accumulation"]

    assert torch.autograd.gradcheck(rendered, (density, rgb))


def test_importance_samples_follow_the_weights():
    bins = torch.linspace(0.0, 4.0, 5).expand(2000, 5)  # four unit bins
    weights = torch.tensor([0.0, 1.0, 3.0, 0.0]).expand(2000, 4)
    torch.manual_seed(0)
    samples = sample_pdf(bins, weights, 16, perturb=True)
    assert samples.shape == (2000, 16)
    assert (samples[:, 1:] >= samples[:, :-1]).all()
    in_bin = torch.stack([((samples >= k) & (samples < k + 1)).float().mean() for k in range(4)])
    torch.testing.assert_close(in_bin, torch.tensor([0.0, 0.25, 0.75, 0.0]), atol=0.01, rtol=0)
    even = sample_pdf(bins[:1], weights[:1], 5, perturb=False)
    # quantiles 1/4, 1/2, 3/4 of that distribution (0 and 1 fall at the ends of the near-empty outer bins)
    torch.testing.assert_close(even[0, 1:4], torch.tensor([2.0, 2 + 1 / 3, 2 + 2 / 3]), atol=1e-3, rtol=0)


def test_padding_keeps_drawing_from_bins_the_weights_call_empty():
    """nerfstudio's histogram padding: weight + 0.01 a bin, so bins of weight 0 keep 0.01 / (1 + 4 x 0.01) of the draws."""
    bins = torch.linspace(0.0, 4.0, 5).expand(2000, 5)
    weights = torch.tensor([0.0, 1.0, 0.0, 0.0]).expand(2000, 4)
    torch.manual_seed(0)
    samples = sample_pdf(bins, weights, 16, perturb=True, padding=0.01)
    in_bin = torch.stack([((samples >= k) & (samples < k + 1)).float().mean() for k in range(4)])
    empty = 0.01 / 1.04
    torch.testing.assert_close(in_bin, torch.tensor([empty, 1.01 / 1.04, empty, empty]), atol=0.003, rtol=0)
