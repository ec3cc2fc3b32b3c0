"""The SSIM map the splat loss differentiates every step, held equal to kornia's in values and gradients; the masks'
opacity loss; the colour correction before the ``cc_`` scores."""

from __future__ import annotations

import math

import kornia
import pytest
import torch

from nerf_lightning.metrics import colour_correct, image_metrics, opacity_mask_loss, ssim_map


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


def test_the_colour_correction_undoes_an_affine_colour_change():
    generator = torch.Generator().manual_seed(0)
    photo = torch.rand(30, 40, 3, generator=generator) * 0.8 + 0.1
    matrix = torch.tensor([[1.2, 0.05, 0.0], [0.0, 0.85, 0.03], [0.02, 0.0, 1.1]])
    bias = torch.tensor([0.03, -0.02, 0.05])
    render = (photo - bias) @ torch.linalg.inv(matrix).T  # the photo = render A^T + b: another exposure and white balance
    assert float(image_metrics(render, photo)["psnr"]) < 25
    assert torch.allclose(colour_correct(render, photo), photo, atol=1e-5)
    # a render that is already right stays so
    assert torch.allclose(colour_correct(photo, photo), photo, atol=1e-6)


def test_a_corrected_render_never_scores_below_the_raw_one_on_a_clipped_background():
    """A small object over a white background the photo clips: fitted over every pixel, the map keeps the background
    white (Zip-NeRF's fit, which leaves the clipped pixels out, moved it far off)."""
    generator = torch.Generator().manual_seed(2)
    photo = torch.ones(40, 40, 3)
    photo[15:25, 15:25] = torch.rand(10, 10, 3, generator=generator) * 0.5
    render = photo * 0.97 + 0.01 * torch.rand(40, 40, 3, generator=generator)
    raw = float(image_metrics(render, photo)["psnr"])
    assert float(image_metrics(colour_correct(render, photo), photo)["psnr"]) >= raw
    flat = torch.full((8, 8, 3), 0.5)
    assert torch.allclose(colour_correct(flat, flat * 0.5 + 0.1), flat * 0.5 + 0.1, atol=1e-6)  # a flat render: a bias fits
    with pytest.raises(ValueError, match=r"colour_correct expects \(H, W, 3\) rgb and target of one shape"):
        colour_correct(render, photo[:4])


def test_with_a_mask_the_colour_correction_is_fitted_to_the_mask_and_leaves_the_rest():
    generator = torch.Generator().manual_seed(1)
    photo = torch.zeros(20, 20, 3)  # the loader's black background round the object
    mask = torch.zeros(20, 20, dtype=torch.bool)
    mask[5:15, 5:15] = True
    photo[mask] = torch.rand(100, 3, generator=generator) * 0.6 + 0.2
    render = photo.clone()
    render[mask] = photo[mask] * 1.2 - 0.05  # the object drawn at another exposure, the background right
    corrected = colour_correct(render, photo, mask)
    assert torch.allclose(corrected, photo, atol=1e-5)
    # fitted to the whole image, the black background pulls the map away from the object's
    assert float(image_metrics(colour_correct(render, photo), photo)["psnr"]) < float(image_metrics(corrected, photo)["psnr"]) - 10
