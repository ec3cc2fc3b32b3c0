"""The SSIM map the splat loss differentiates every step, held equal to kornia's in values and gradients; the masks' opacity loss."""

from __future__ import annotations

import math

import kornia
import pytest
import torch

from nerf_lightning.metrics import opacity_mask_loss, ssim_map


@pytest.mark.parametrize("size", [(1, 3, 37, 53), (2, 1, 16, 12)])
def test_the_ssim_map_is_kornias_in_values_and_gradients(size: tuple[int, ...]) -> None:
    generator = torch.Generator().manual_seed(0)
    target = torch.rand(size, generator=generator)
    # an image near the target (SSIM's interesting range) and one far from it
    for image in (target + 0.05 * torch.randn(size, generator=generator), torch.rand(size, generator=generator)):
        image = image.clamp(0.0, 1.0).requires_grad_()
        weights = torch.rand(size, generator=generator)
        reference = kornia.metrics.ssim(image, target, window_size=11)
        ours = ssim_map(image, target)
        torch.testing.assert_close(ours, reference, atol=1e-6, rtol=1e-5)
        grad_reference, = torch.autograd.grad((reference * weights).sum(), image)
        grad_ours, = torch.autograd.grad((ours * weights).sum(), image)
        scale = grad_reference.abs().max()  # float32 sums in another order: compared to the largest gradient
        torch.testing.assert_close(grad_ours / scale, grad_reference / scale, atol=1e-5, rtol=0.0)


def test_the_ssim_map_refuses_mismatched_images() -> None:
    with pytest.raises(ValueError, match=r"\(1, 3, 8, 8\) and \(1, 3, 8, 9\)"):
        ssim_map(torch.rand(1, 3, 8, 8), torch.rand(1, 3, 8, 9))


def test_the_mask_loss_is_the_binary_cross_entropy_over_the_pixels_it_weighs():
    opacity = torch.tensor([0.9, 0.2, 0.5, 0.7])
    mask = torch.tensor([True, False, True, False])
    entropy = -torch.stack([torch.log(torch.tensor(0.9)), torch.log(torch.tensor(0.8)), torch.log(torch.tensor(0.5)),
                            torch.log(torch.tensor(0.3))])
    assert float(opacity_mask_loss(opacity, mask)) == pytest.approx(float(entropy.mean()), rel=1e-5)
    # a ray left out (weight 0: a fixed capacity cut it short) counts for nothing
    weight = torch.tensor([1.0, 1.0, 1.0, 0.0])
    assert float(opacity_mask_loss(opacity, mask, weight)) == pytest.approx(float(entropy[:3].mean()), rel=1e-5)
    # right to the clamp: finite, and near zero
    assert float(opacity_mask_loss(torch.tensor([1.0, 0.0]), torch.tensor([True, False]))) == pytest.approx(-math.log(1 - 1e-3), rel=1e-3)
