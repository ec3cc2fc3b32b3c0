"""The fused numba photometric loss equals the PyTorch reference (splats/loss.py) in values and gradients."""

from __future__ import annotations

import pytest
import torch

from nerf_lightning.splats.loss import photometric_loss
from nerf_lightning.splats.loss_fast import photometric_loss_fast


def pair(height: int, width: int, dtype: torch.dtype, seed: int = 0) -> tuple[torch.Tensor, torch.Tensor]:
    generator = torch.Generator().manual_seed(seed)
    rgb = torch.rand(height, width, 3, generator=generator, dtype=dtype)
    image = torch.rand(height, width, 3, generator=generator, dtype=dtype)
    return rgb.requires_grad_(), image


def both(rgb, image, weight, mask):
    reference = photometric_loss(rgb, image, weight, mask)
    (reference_grad,) = torch.autograd.grad(reference * 2.5, rgb)  # an upstream gradient that is not 1
    fast, mse = photometric_loss_fast(rgb, image, weight, mask)
    (fast_grad,) = torch.autograd.grad(fast * 2.5, rgb)
    return reference, reference_grad, fast, fast_grad, mse


# 6 is the smallest side reflect padding of 5 allows; odd sides, a wide and a tall view, one larger than the window
@pytest.mark.parametrize("size", [(6, 6), (7, 13), (40, 9), (33, 47)])
@pytest.mark.parametrize("masked", [False, True])
@pytest.mark.parametrize("weight", [0.2, 0.0, 1.0])
def test_the_fused_loss_is_the_reference_in_values_and_gradients_in_float64(size, masked, weight):
    rgb, image = pair(*size, torch.float64)
    mask = torch.rand(size, generator=torch.Generator().manual_seed(1)) > 0.4 if masked else None
    reference, reference_grad, fast, fast_grad, mse = both(rgb, image, weight, mask)
    torch.testing.assert_close(fast, reference.detach(), rtol=1e-12, atol=1e-14)
    torch.testing.assert_close(fast_grad, reference_grad, rtol=1e-10, atol=1e-14)
    assert mse == pytest.approx(float(((rgb - image) ** 2).mean()), rel=1e-12)


def test_the_fused_loss_agrees_in_float32_and_at_the_edges():
    rgb, image = pair(64, 48, torch.float32)
    reference, reference_grad, fast, fast_grad, _ = both(rgb, image, 0.2, None)
    assert fast.dtype == torch.float32 and fast_grad.dtype == torch.float32
    torch.testing.assert_close(fast, reference.detach(), rtol=1e-5, atol=1e-6)
    torch.testing.assert_close(fast_grad, reference_grad, rtol=1e-4, atol=1e-7)
    # a perfect render: L1 0, SSIM 1, and where rgb = image the L1's sign is 0 (as torch's abs backward has it)
    same = image.clone().requires_grad_()
    reference, reference_grad, fast, fast_grad, mse = both(same, image, 0.2, None)
    assert float(fast) == pytest.approx(0.0, abs=1e-6) and mse == 0.0
    torch.testing.assert_close(fast_grad, reference_grad, rtol=1e-4, atol=1e-7)
    # an empty mask: nothing counts, a zero loss and gradient, as the reference's mean over none
    empty = torch.zeros(64, 48, dtype=torch.bool)
    reference, reference_grad, fast, fast_grad, _ = both(rgb, image, 0.2, empty)
    assert float(fast) == pytest.approx(float(reference), abs=1e-7) and float(fast_grad.abs().max()) == 0.0


def test_the_fused_loss_gives_the_same_bits_every_time():
    rgb, image = pair(96, 80, torch.float32)
    first, _ = photometric_loss_fast(rgb, image, 0.2)
    (first_grad,) = torch.autograd.grad(first, rgb)
    for _ in range(3):
        again, _ = photometric_loss_fast(rgb, image, 0.2)
        (again_grad,) = torch.autograd.grad(again, rgb)
        assert torch.equal(again, first) and torch.equal(again_grad, first_grad)


def test_the_fused_loss_refuses_what_it_cannot_score():
    with pytest.raises(ValueError, match="one shape"):
        photometric_loss_fast(torch.rand(8, 8, 3), torch.rand(8, 9, 3), 0.2)
    with pytest.raises(ValueError, match="larger than 5 pixels"):
        photometric_loss_fast(torch.rand(5, 8, 3), torch.rand(5, 8, 3), 0.2)
    with pytest.raises(ValueError, match="mask must be"):
        photometric_loss_fast(torch.rand(8, 8, 3), torch.rand(8, 8, 3), 0.2, torch.ones(8, 7, dtype=torch.bool))
