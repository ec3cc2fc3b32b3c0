"""The splats' photometric loss and its gradient in one numba pass a direction on a CPU: the idea of fused-ssim,
Taming 3DGS and Brush, beside the PyTorch reference :func:`~nerf_lightning.splats.loss.photometric_loss` that the
tests hold it equal to (values and gradients, float64, masks, borders).

The reference runs some fifty tensor operations forward and as many backward (the five moments stacked, padded,
blurred by two grouped convolutions, then the SSIM formula term by term, each a pass over the image and a launch on
a GPU). Here, for an image x (H, W, C) against y:

- **forward**: the five moments x, y, x^2, y^2, xy blurred by the separable 11-tap Gaussian (sigma 1.5) with
  reflect borders, a pass along the rows and one along the columns; then each pixel's SSIM
  S = (2 mx my + C1)(2 sxy + C2) / ((mx^2 + my^2 + C1)(sx^2 + sy^2 + C2)), its L1, and the three partial derivatives
  of S in the blurred moments that involve x: dS/dmx, dS/d(x^2 blurred), dS/d(xy blurred), weighted by the pixel's
  share of the mean;
- **backward**: those three maps blurred by the blur's transpose (the reflect border folded back: a scatter), so that
  dL/dx = (1 - w) sign(x - y) share - w (B^T a + 2 x B^T b + y B^T c).

Sums are taken row by row and then in row order, so the same input gives the same loss bit for bit whatever the
threads do. The image is the photo, never differentiated.
"""

from __future__ import annotations

import numba
import numpy as np
import torch

# SSIM's window (kornia's, and 3DGS's): 11 taps, sigma 1.5; its stabilising constants for values in [0, 1]
WINDOW, SIGMA = 11, 1.5
C1, C2 = 0.01**2, 0.03**2


def gaussian_window(dtype: np.dtype) -> np.ndarray:
    """(WINDOW,) the normalised 1D Gaussian kornia's ``get_gaussian_kernel1d(11, 1.5)`` gives, in ``dtype``."""
    offsets = np.arange(WINDOW, dtype=np.float64) - WINDOW // 2
    window = np.exp(-(offsets**2) / (2.0 * SIGMA**2))
    return (window / window.sum()).astype(dtype)


@numba.njit(inline="always")
def _reflect(index, size):
    """``index`` in [-size + 1, 2 size - 2] folded into [0, size) as torch's reflect padding folds it."""
    if index < 0:
        return -index
    if index >= size:
        return 2 * (size - 1) - index
    return index


@numba.njit(cache=True, parallel=True)
def loss_forward(x, y, mask, masked, ssim_weight, window, partials, signs, row_sums):
    """x, y (H, W, C); mask (H, W) bool, read where ``masked`` -> fills ``partials`` (H, W, 3, C): the pixels'
    share-weighted dS/dmx, dS/dEx2, dS/dExy; ``signs`` (H, W, C): the share-weighted sign of x - y; ``row_sums``
    (H, 3): each row's weighted L1 and SSIM sums and its squared error. Returns the loss's L1 and SSIM means."""
    height, width, channels = x.shape
    radius = window.shape[0] // 2
    count = 0
    if masked:
        for i in range(height):
            for j in range(width):
                count += mask[i, j]
    share = 1.0 / (max(count, 1) if masked else height * width) / channels
    along_rows = np.empty((height, width, 5, channels), x.dtype)
    for i in numba.prange(height):
        for j in range(width):
            for c in range(channels):
                m0 = m1 = m2 = m3 = m4 = 0.0
                for k in range(window.shape[0]):
                    jj = _reflect(j + k - radius, width)
                    a, b, g = x[i, jj, c], y[i, jj, c], window[k]
                    m0 += g * a
                    m1 += g * b
                    m2 += g * a * a
                    m3 += g * b * b
                    m4 += g * a * b
                along_rows[i, j, 0, c], along_rows[i, j, 1, c], along_rows[i, j, 2, c] = m0, m1, m2
                along_rows[i, j, 3, c], along_rows[i, j, 4, c] = m3, m4
    for i in numba.prange(height):
        l1_sum = ssim_sum = squared = 0.0
        for j in range(width):
            weight = share if not masked else (share if mask[i, j] else 0.0)
            for c in range(channels):
                mx = my = exx = eyy = exy = 0.0
                for k in range(window.shape[0]):
                    ii = _reflect(i + k - radius, height)
                    g = window[k]
                    mx += g * along_rows[ii, j, 0, c]
                    my += g * along_rows[ii, j, 1, c]
                    exx += g * along_rows[ii, j, 2, c]
                    eyy += g * along_rows[ii, j, 3, c]
                    exy += g * along_rows[ii, j, 4, c]
                a1 = 2.0 * mx * my + C1
                a2 = 2.0 * (exy - mx * my) + C2
                b1 = mx * mx + my * my + C1
                b2 = (exx - mx * mx) + (eyy - my * my) + C2
                denominator = b1 * b2 + 1e-12
                s = a1 * a2 / denominator
                d_mx = (2.0 * my * a2 - 2.0 * my * a1) / denominator - s / denominator * (2.0 * mx * b2 - 2.0 * mx * b1)
                partials[i, j, 0, c] = weight * d_mx
                partials[i, j, 1, c] = weight * (-s / denominator * b1)
                partials[i, j, 2, c] = weight * (2.0 * a1 / denominator)
                difference = x[i, j, c] - y[i, j, c]
                signs[i, j, c] = weight * ((difference > 0) - (difference < 0))
                l1_sum += weight * abs(difference)
                ssim_sum += weight * s
                squared += difference * difference
        row_sums[i, 0], row_sums[i, 1], row_sums[i, 2] = l1_sum, ssim_sum, squared


@numba.njit(inline="always")
def _blur_transposed(source, window, target):
    """Adds to ``target`` (n, 3, C) the transpose of the reflect-bordered blur along the first axis applied to
    ``source`` (n, 3, C): each value spread over the window onto the places it was read from."""
    size, radius = source.shape[0], window.shape[0] // 2
    for i in range(size):
        for k in range(window.shape[0]):
            ii = _reflect(i + k - radius, size)
            g = window[k]
            for m in range(source.shape[1]):
                for c in range(source.shape[2]):
                    target[ii, m, c] += g * source[i, m, c]


@numba.njit(cache=True, parallel=True)
def loss_backward(x, y, partials, signs, ssim_weight, window, scale, grad):
    """The gradient of the loss, times ``scale`` (the upstream gradient), into ``grad`` (H, W, C) from what
    :func:`loss_forward` kept: the partials blurred by the transposed blur (columns, then rows), then the chain rule
    through the moments x, x^2 and xy."""
    height, width, channels = x.shape
    down = np.zeros((height, width, 3, channels), x.dtype)
    for j in numba.prange(width):  # the transpose of the blur along the columns: each output column its own thread's
        _blur_transposed(partials[:, j], window, down[:, j])
    for i in numba.prange(height):  # then along the rows, each row its own thread's
        across = np.zeros((width, 3, channels), x.dtype)
        _blur_transposed(down[i], window, across)
        for j in range(width):
            for c in range(channels):
                d_ssim = across[j, 0, c] + 2.0 * x[i, j, c] * across[j, 1, c] + y[i, j, c] * across[j, 2, c]
                grad[i, j, c] = scale * ((1.0 - ssim_weight) * signs[i, j, c] - ssim_weight * d_ssim)


class FusedPhotometricLoss(torch.autograd.Function):
    """rgb (H, W, C), image (H, W, C), mask (H, W) bool or None, ssim_weight -> the loss () and the mean squared
    error over the whole image (a float, for the logged PSNR); differentiable in rgb."""

    @staticmethod
    def forward(ctx, rgb, image, mask, ssim_weight: float):
        x = rgb.detach().contiguous().numpy()
        y = image.detach().to(rgb.dtype).contiguous().numpy()
        masked = mask is not None
        mask_array = mask.detach().contiguous().numpy() if masked else np.ones((1, 1), np.bool_)
        height, width, channels = x.shape
        window = gaussian_window(x.dtype)
        partials = torch.empty((height, width, 3, channels), dtype=rgb.dtype).numpy()
        signs = torch.empty((height, width, channels), dtype=rgb.dtype).numpy()
        row_sums = np.empty((height, 3), np.float64)
        loss_forward(x, y, mask_array, masked, ssim_weight, window, partials, signs, row_sums)
        l1, ssim, squared = row_sums.sum(axis=0)  # in row order: the same sum every time
        ctx.saved = (x, y, partials, signs, ssim_weight, window)
        loss = (1.0 - ssim_weight) * l1 + ssim_weight * (1.0 - ssim)
        return torch.from_numpy(np.asarray(loss, dtype=x.dtype)), float(squared / x.size)

    @staticmethod
    def backward(ctx, grad_loss, _mse):
        x, y, partials, signs, ssim_weight, window = ctx.saved
        grad = torch.empty(x.shape, dtype=grad_loss.dtype)
        loss_backward(x, y, partials, signs, ssim_weight, window, grad_loss.detach().numpy().item(), grad.numpy())
        return grad, None, None, None


def photometric_loss_fast(rgb: torch.Tensor, image: torch.Tensor, ssim_weight: float,
                          mask: torch.Tensor | None = None) -> tuple[torch.Tensor, float]:
    """:func:`~nerf_lightning.splats.loss.photometric_loss` of CPU rgb (H, W, C) against image (H, W, C) (mask
    (H, W) bool or None), in one numba pass, and the mean squared error of rgb against image over every pixel (for
    the logged PSNR). H and W must exceed the window's radius (5), as the reference's reflect padding needs."""
    if rgb.shape != image.shape or rgb.ndim != 3:
        raise ValueError(f"photometric_loss_fast expects (H, W, C) rgb and image of one shape, got {tuple(rgb.shape)} "
                         f"and {tuple(image.shape)}")
    if min(rgb.shape[:2]) <= WINDOW // 2:
        raise ValueError(f"photometric_loss_fast needs views larger than {WINDOW // 2} pixels a side (SSIM's reflect "
                         f"padding), got {tuple(rgb.shape[:2])}")
    if mask is not None and mask.shape != rgb.shape[:2]:
        raise ValueError(f"photometric_loss_fast's mask must be (H, W) = {tuple(rgb.shape[:2])}, got {tuple(mask.shape)}")
    return FusedPhotometricLoss.apply(rgb, image, mask, float(ssim_weight))
