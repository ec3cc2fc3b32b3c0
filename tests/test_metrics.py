"""The SSIM map the splat loss differentiates every step, held equal to kornia's in values and gradients."""

from __future__ import annotations

import kornia
import pytest
import torch

from nerf_lightning.metrics import ssim_map


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
